"""Queue recovery on both brokers the project supports (the embedded SQLAlchemy transport and
Redis), with real workers: a queued job is sent again only when its broker message is really
gone (never sent, or delivered to a worker that died before claiming it), not because it waited
long; a duplicate delivery is dropped with a log line and no traceback; scratch folders left by
a killed worker are removed when a worker starts."""

from __future__ import annotations

import datetime as dt
import os
import secrets
import subprocess
import sys
from pathlib import Path

import pytest
from sqlalchemy import update
from worker_harness import ROOT, add_capture, tiny_config, wait_for

from worker.blobs import open_store
from worker.broker import BrokerInspector, job_of_message
from worker.celery_app import dispatch, make_celery
from worker.db import migrate
from worker.models import Job, utcnow
from worker.settings import WorkerSettings
from worker.store import JobStore, Owner
from worker.sweeper import Sweeper

pytestmark = pytest.mark.timeout(600)

# A worker that takes the first message of the queue and dies before it claims the job.
TAKE_AND_DIE = """
import os
from worker.celery_app import make_celery
from worker.settings import WorkerSettings
settings = WorkerSettings()
with make_celery(settings).connection_for_read() as conn:
    queue = conn.SimpleQueue(settings.queue, no_ack=False)
    message = queue.get(timeout=30)
    print(message.headers["task"], flush=True)
    os._exit(0)  # no ack, no clean close: the message dies with this process
"""


@pytest.fixture(params=["embedded", "redis"])
def stack(request, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """(environment of worker processes, settings of this process)."""
    # Leases and the lost-message grace generous enough that a loaded machine (a child that
    # takes seconds to claim its job, a heartbeat thread starved) changes nothing.
    env = {"DGS_DATA_DIR": str(tmp_path / "data"), "DGS_LEASE_SECONDS": "20",
           "DGS_HEARTBEAT_SECONDS": "0.5", "DGS_LOST_MESSAGE_SECONDS": "20",
           "DGS_QUEUE": f"q-{secrets.token_hex(4)}", "OMP_NUM_THREADS": "1"}
    if request.param == "redis":
        url, prefix = request.getfixturevalue("redis_broker")
        env.update({"DGS_BROKER_URL": url, "DGS_REDIS_KEY_PREFIX": prefix})
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    settings = WorkerSettings()
    migrate(settings.database)
    return {**os.environ, **env}, settings


def _send(store: JobStore, app, settings, job_id: str) -> None:
    store.mark_dispatched(job_id)
    dispatch(app, settings, job_id, "reconstruct")


def _sent_hours_ago(store: JobStore, *job_ids: str) -> None:
    with store.session() as s:
        s.execute(update(Job).where(Job.id.in_(job_ids)).values(
            dispatched_at=utcnow() - dt.timedelta(hours=10)))


def test_the_broker_says_which_queued_jobs_it_still_holds(stack):
    env, settings = stack
    store, app = JobStore(settings.database), make_celery(settings)
    taken, waiting, lost = (store.create("t1", "reconstruct", {}, capture_id=None).id
                            for _ in range(3))
    _send(store, app, settings, taken)
    out = subprocess.run([sys.executable, "-c", TAKE_AND_DIE], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.stdout.strip() == "dgs.run_job", out.stderr
    _send(store, app, settings, waiting)
    store.mark_dispatched(lost)  # recorded as sent; the message never reached the broker
    inspector = BrokerInspector(app, settings)
    assert inspector.held_jobs(grace=3600) == {taken, waiting}  # taken: maybe being claimed
    assert inspector.held_jobs(grace=1e-3) == {waiting}  # taken's worker never claimed it
    _sent_hours_ago(store, taken, waiting, lost)
    sent: list[str] = []
    fast = settings.model_copy(update={"lost_message_seconds": 1e-3, "lease_seconds": 1e-3})
    result = Sweeper(fast, sent.append, store=store, held=inspector.held_jobs).sweep()
    assert sorted(sent) == sorted([taken, lost]) == sorted(result["redispatched"])
    assert store.get(waiting).dispatches == 1  # waited ten hours, its message is there: kept


def test_job_of_message_reads_only_our_task():
    import base64
    import json

    body = base64.b64encode(json.dumps([["job_1"], {}, {}]).encode()).decode()
    message = {"body": body, "headers": {"task": "dgs.run_job"},
               "properties": {"body_encoding": "base64"}}
    assert job_of_message(message) == "job_1" and job_of_message(json.dumps(message)) == "job_1"
    assert job_of_message({**message, "headers": {"task": "other"}}) is None
    assert job_of_message({"body": "%%%"}) is None and job_of_message("not json") is None


def test_lost_messages_are_sent_again_and_duplicates_dropped_quietly(stack, tiny_capture: Path,
                                                                     worker_factory, tmp_path):
    env, settings = stack
    store, app = JobStore(settings.database), make_celery(settings)
    blobs = open_store(settings.storage)
    cap = add_capture(store, blobs, tiny_capture)

    def job(iterations: int) -> str:
        return store.create("t1", "reconstruct", {"preset": "test",
                            "config": tiny_config(iterations)}, capture_id=cap).id

    running, waiting, lost = job(120), job(30), job(30)
    _send(store, app, settings, running)
    _send(store, app, settings, waiting)
    _sent_hours_ago(store, waiting)  # long in the queue, but its message is there
    store.mark_dispatched(lost)  # its message is lost
    ended = store.create("t1", "reconstruct", {}, capture_id=None).id
    owner = Owner.current()
    store.claim(ended, owner, 5, 3)
    store.finish(ended, owner, "failed")
    left = [settings.scratch / "jobs" / ended / "run", settings.scratch / "jobs" / "job_gone"]
    for folder in left:  # what a SIGKILLed worker left behind
        folder.mkdir(parents=True)
    worker = worker_factory(env, "--concurrency", "2").start()
    wait_for(lambda: all(not f.parent.exists() or f.name == "job_gone" and not f.exists()
                         for f in left), 60, "the start-up sweep to remove stale folders")
    wait_for(lambda: (store.get(running).iteration or 0) >= 10, 240, "the first job to run")
    dispatch(app, settings, running, "reconstruct")  # a duplicate delivery while it runs
    for job_id in (running, waiting, lost):
        wait_for(lambda: store.get(job_id).state in ("succeeded", "failed"), 300,
                 f"job {job_id} to end")
        assert store.get(job_id).state == "succeeded"
        assert store.get(job_id).attempts == 1  # never run twice
        assert not (settings.scratch / "jobs" / job_id).exists()
    # waiting was never sent twice; lost at least once more (again if a busy worker held its
    # new message unclaimed for a lease: harmless, the duplicate is dropped)
    assert store.get(waiting).dispatches == 1 and store.get(lost).dispatches >= 2

    def told() -> str | None:  # the worker has logged the re-send and the dropped duplicate
        text = worker.log.read_text(errors="replace")
        return text if f"job {lost}: sent to the queue again: it is queued, but its message " \
            "is no longer in the broker" in text and f"job {running}: it " in text else None

    try:
        log = wait_for(told, 120, "the worker to log the re-send and the duplicate")
    except BaseException:
        print(worker.log.read_text(errors="replace")[-6000:])
        raise
    # Dropped in the Celery parent (worker.gate), or, when it came in before the job's claim,
    # by the pool process's own claim.
    assert "its message is dropped (no pool process started)" in log \
        or "this duplicate message is dropped" in log, log[-4000:]
    assert f"job {waiting}: sent to the queue again" not in log
    for noise in ("Traceback", "MaxRetriesExceeded", "Retry in", "its worker is gone"):
        assert noise not in log, log[-4000:]
