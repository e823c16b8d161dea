"""Fixtures for the worker tests: job stores on SQLite and PostgreSQL, a tiny capture, and real
`dgs worker` processes (helpers in worker_harness.py)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest
from sqlalchemy import select
from worker_harness import WorkerProcess

from worker.db import migrate
from worker.models import Job, JobLog
from worker.store import JobStore


@pytest.fixture(autouse=True)
def job_errors_name_no_server_folder(tmp_path_factory, monkeypatch):
    """Every job error, message and log line a test leaves in a job store (its own, or a
    worker's) names no folder under the session's temporary folder, where each test's data
    and scratch folders live, unless the job's own parameters sent that path."""
    urls: set[str] = set()
    init = JobStore.__init__

    def record(self, url: str) -> None:
        init(self, url)
        urls.add(url)

    monkeypatch.setattr(JobStore, "__init__", record)
    yield
    folder = str(tmp_path_factory.getbasetemp())
    leaks = []
    for url in urls:
        with JobStore(url).session(write=False) as s:
            for job in s.scalars(select(Job)):
                texts = [json.dumps(job.error or {}), job.message or ""] + list(s.scalars(
                    select(JobLog.line).where(JobLog.job_id == job.id)))
                leaks += [f"{job.id}: {t[:300]}" for t in texts
                          if folder in t and folder not in json.dumps(job.params)]
    assert not leaks, "job errors name server folders:\n" + "\n".join(leaks[:20])


@pytest.fixture(params=["sqlite", "postgres"])
def store_url(request, tmp_path: Path) -> str:
    """A migrated, empty job store on each backend."""
    if request.param == "sqlite":
        url = f"sqlite:///{tmp_path / 'dgs.sqlite3'}"
        migrate(url)
        return url
    return request.getfixturevalue("pg_empty")


@pytest.fixture
def store(store_url: str) -> JobStore:
    return JobStore(store_url)


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """8 views of 32x32, one frame, masks and ground truth (2 held-out cameras)."""
    from core.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("worker-capture") / "capture"
    synthesize(out, SynthConfig(frames=1, views=8, width=32, height=32, seed=2, ao_directions=8))
    return out


@pytest.fixture
def worker_factory(tmp_path: Path) -> Callable[[dict[str, str]], WorkerProcess]:
    """Makes real worker processes; stops them after the test."""
    started: list[WorkerProcess] = []

    def make(env: dict[str, str], *args: str) -> WorkerProcess:
        w = WorkerProcess(env, tmp_path / "worker.log", args)
        started.append(w)
        return w

    yield make
    for w in started:
        w.stop()
