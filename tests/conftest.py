"""Session fixtures shared by tests/worker and tests/service: the real PostgreSQL and Redis;
and the device training's `auto` picks in every test (the CPU)."""

from __future__ import annotations

import os

import pytest

# `make test` runs the suite in pytest-xdist processes (one a core): each keeps to its share of
# the cores, so that two processes' OpenMP threads do not fight over them (set before anything
# loads torch; a value the user set is kept).
if os.environ.get("PYTEST_XDIST_WORKER"):
    _share = (os.cpu_count() or 1) // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, _share)))

import core  # noqa: E402,F401  (before any test module loads torch: OpenMP's passive wait)
import real_services as services

# Training's device `auto` means the CPU in the tests, also in the processes they start (workers,
# CLI runs): STYLE 12, and the exact-resume checks hold on the CPU only (CUDA's atomic gradient
# sums are not bit-reproducible). GPU tests name `cuda`; DGS_DEVICE=cuda runs the rest there too.
os.environ.setdefault("DGS_DEVICE", "cpu")


@pytest.fixture(scope="session")
def pg_url():
    """URL of a fresh PostgreSQL database (dropped at the end of the session)."""
    yield from services.postgres_database()


@pytest.fixture
def pg_empty(pg_url: str) -> str:
    """`pg_url`'s database migrated and emptied for this test. The database is one a session:
    a test before may have left jobs, captures or an API key (the API then asks every caller
    for a key, and a test without one gets 401)."""
    from sqlalchemy import text

    from worker.db import engine_for, migrate

    migrate(pg_url)
    with engine_for(pg_url).begin() as c:
        c.execute(text("TRUNCATE api_keys, captures, uploads, jobs, job_events, job_logs, "
                       "idempotency_keys, artifacts, assets, rate_buckets"))
    return pg_url


@pytest.fixture(scope="session")
def redis_broker():
    """(Redis URL, key prefix) private to this session."""
    yield from services.redis_namespace()


# The files that take longest (each a minute or more of live servers, Celery workers or the
# browser; CI's --durations), run first: `make test` hands out whole files to its processes, and a
# long file started last is a tail with one process working.
LONG_FILES = ("worker/test_celery.py", "worker/test_watchdog.py", "test_docs.py",
              "worker/test_requeue.py", "service/test_api_parts_live.py", "worker/test_gate.py",
              "service/test_demo.py", "worker/test_parts_celery.py", "e2e/test_web_parts.py",
              "core/test_sequence.py", "service/test_api_door_live.py", "e2e/test_player.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONG_FILES)}
    root = config.rootpath / "tests"

    def key(item):
        try:
            name = item.path.relative_to(root).as_posix()
        except ValueError:
            return len(LONG_FILES)
        return rank.get(name, len(LONG_FILES))

    items.sort(key=key)  # stable: the order within each group is kept
