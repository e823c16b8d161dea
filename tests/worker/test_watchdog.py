"""The watchdog of a worker's pool (worker.watchdog, issue 42): a pool process that stopped making
progress (its lease lapsed, or it held none for `stall_seconds`) is killed, so its slot frees
and its job runs again from its checkpoint, once. First the rule against a real job store,
then real workers whose pool process is made to hang as the one of issue 42 did
(worker.faults: a deadlock holding the GIL), before its claim and after it."""

from __future__ import annotations

import datetime as dt
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from sqlalchemy import update
from test_celery import Harness, s3_server, stack  # noqa: F401  (fixtures)
from worker_harness import wait_for

from worker.models import Job, utcnow
from worker.lease import lease_prefix
from worker.settings import WorkerSettings
from worker.store import JobStore, Owner
from worker.watchdog import Watchdog

pytestmark = pytest.mark.timeout(600)


def _owner(pid: int) -> Owner:
    return Owner.parse(lease_prefix(pid) + "tok")


def _claimed(store: JobStore, pid: int, lease_left: float) -> str:
    job = store.create("t1", "reconstruct", {"preset": "test"}, capture_id=None)
    assert store.claim(job.id, _owner(pid), 60, 3).status == "claimed"
    with store.session() as s:
        s.execute(update(Job).where(Job.id == job.id).values(
            lease_expires_at=utcnow() + dt.timedelta(seconds=lease_left)))
    return job.id


def test_a_busy_process_is_killed_when_its_lease_lapses_or_it_holds_none(store: JobStore,
                                                                         tmp_path: Path):
    sleepers = [subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
                for _ in range(3)]
    try:
        live, lapsed, never = (p.pid for p in sleepers)
        busy = {live: _claimed(store, live, 600), lapsed: _claimed(store, lapsed, -1),
                never: "job_not_claimed_yet"}
        killed: list[int] = []
        settings = WorkerSettings(data_dir=tmp_path, database_url=store.url, stall_seconds=3)
        dog = Watchdog(settings, lambda: dict(busy), store=store, kill=killed.append)
        assert set(dog.check()) == {lapsed} and killed == [lapsed]  # the lapsed lease at once
        del busy[lapsed]
        wait_for(lambda: dog.check() or killed[1:], 60, "the stall limit")
        assert killed == [lapsed, never]  # no lease for 3 s; the live lease is left alone
        del busy[never]
        # A process that had a live lease and then none (its job ended) gets the same time.
        store.finish(busy[live], _owner(live), "succeeded")
        wait_for(lambda: dog.check() or killed[2:], 60, "the stall limit")
        assert killed[2:] == [live]
    finally:
        for p in sleepers:
            p.kill()
            p.wait()
        # Leave no running job behind in the session's database: the sweepers of later tests'
        # workers would send it to their queues.
        with store.session() as s:
            s.execute(update(Job).where(Job.state == "running").values(
                state="cancelled", lease_owner=None, lease_expires_at=None))


@pytest.mark.parametrize("where", ["start", "claimed"])
def test_a_hung_pool_process_is_killed_and_its_job_succeeds_once(stack, tiny_capture: Path,
                                                                 worker_factory, tmp_path: Path,
                                                                 where: str):
    env, settings = stack
    h = Harness(settings, tiny_capture)
    marker = tmp_path / "hung"
    worker = worker_factory({**env, "DGS_FAULT_HANG": f"{where}:{marker}",
                             "DGS_STALL_SECONDS": "20"}).start()
    job_id = h.submit(iterations=60)
    wait_for(marker.exists, 300, "a pool process to hang")
    done = h.wait_state(job_id, ("succeeded", "failed"), timeout=300)
    assert done.state == "succeeded", h.log(job_id)
    text = worker.log.read_text(errors="replace")
    assert f"(job {job_id})" in text and "killed; its job goes back to the queue" in text
    why = "stopped renewing the lease" if where == "claimed" else "has held no live lease"
    assert why in text
    outcomes = [r.get("outcome") for r in done.runs]
    assert outcomes.count("succeeded") == 1 and outcomes[-1] == "succeeded"
    states = [e.data["state"] for e in h.store.events_after(job_id, 0)
              if e.kind == "state" and "state" in e.data]
    assert states.count("succeeded") == 1
    # The hung attempt wrote nothing after it hung: claimed, it is a lost run before the one
    # that succeeded; hung before its claim, it never ran.
    assert outcomes == (["lost", "succeeded"] if where == "claimed" else ["succeeded"])
    assert done.attempts == len(outcomes)


def test_a_warm_shutdown_waits_no_longer_than_the_watchdog(stack, tiny_capture: Path,
                                                           worker_factory, tmp_path: Path):
    """SIGTERM to a worker whose pool process is stuck (what `dgs serve` dying does to its
    embedded worker): the warm shutdown waits for the task, the watchdog ends the stuck
    process when its lease lapses, and the worker exits; the next worker resumes the job."""
    env, settings = stack
    h = Harness(settings, tiny_capture)
    marker = tmp_path / "hung"
    first = worker_factory({**env, "DGS_FAULT_HANG": f"claimed:{marker}"}).start()
    job_id = h.submit(iterations=60)
    wait_for(marker.exists, 300, "a pool process to hang")
    os.kill(first.proc.pid, signal.SIGTERM)
    first.proc.wait(timeout=240)
    assert "killed; its job goes back to the queue" in first.log.read_text(errors="replace")
    worker_factory(env).start()
    done = h.wait_state(job_id, ("succeeded", "failed"), timeout=300)
    assert done.state == "succeeded", h.log(job_id)
    assert [r.get("outcome") for r in done.runs][-1] == "succeeded"
