"""Messages with nothing to run are dropped in the Celery parent (worker.gate, issue 42): a flood
of messages for cancelled, finished and deleted jobs starts no pool process (each used to cost
a fresh one, torch imported, before the next job could run), and the live job behind them runs
without waiting for one per message. A message whose tenant has not the turn (worker.fair) goes
back to the queue from the parent: another tenant's job runs before a tenant's queue, and each
job still runs once."""

from __future__ import annotations

import secrets
from pathlib import Path

import pytest
from sqlalchemy import update
from test_celery import Harness, s3_server, stack  # noqa: F401  (fixtures)
from worker_harness import add_capture, tiny_config, wait_for

from worker.broker import BrokerInspector
from worker.celery_app import dispatch
from worker.models import Job
from worker.store import ACTIVE

pytestmark = pytest.mark.timeout(600)


def pool_processes(worker_pid: int) -> set[int]:
    """Pids of the pool processes of the Celery worker `worker_pid` (spawned interpreters)."""
    out = set()
    for entry in Path("/proc").glob("[0-9]*"):
        try:
            stat = (entry / "stat").read_text()
            cmd = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == worker_pid and b"spawn_main" in cmd:
            out.add(int(entry.name))
    return out


def _loaded(pid: int, library: str) -> bool:
    try:
        return library in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


def test_dead_messages_start_no_pool_process(stack, tiny_capture: Path, worker_factory):
    env, settings = stack
    h = Harness(settings, tiny_capture)
    worker = worker_factory(env).start()
    idle = wait_for(lambda: pool_processes(worker.proc.pid), 120, "the idle pool process")
    # It loads torch as it starts, before any job (its first job starts as fast as the next).
    wait_for(lambda: all(_loaded(pid, "libtorch") for pid in idle), 300, "torch in the idle "
             "pool process")
    dead = []
    for i in range(15):  # a tenant's retry/cancel pairs: each leaves a message behind
        job = h.store.create("t1", "reconstruct", {"preset": "test"}, capture_id=h.capture_id)
        h.store.request_cancel(job.id, "t1")
        dead.append(job.id)
    done = h.submit(iterations=20)
    assert h.wait_state(done, ("succeeded", "failed")).state == "succeeded"
    dead.append(done)  # finished
    dead.append(f"job_{secrets.token_hex(10)}")  # deleted (never existed)
    for job_id in dead:
        dispatch(h.celery, settings, job_id, "reconstruct")
    live = h.submit(iterations=20)
    job = h.wait_state(live, ("succeeded", "failed"))
    assert job.state == "succeeded", h.log(live)
    text = worker.log.read_text(errors="replace")
    dropped = text.count("its message is dropped (no pool process started)")
    assert dropped == len(dead), text[-3000:]
    # The two jobs that ran shared the pool process the worker started with (kept between
    # tasks); a message dropped in the parent started none (before the gate, each of the 17
    # did). Two more are allowed for replacements the pool makes on its own, as when a busy
    # machine keeps a fresh process from reporting for work in time.
    started = text.count("calling self.run()")
    assert 1 <= started <= 3, text[-3000:]
    assert started < len(dead), text[-3000:]
    # None is left waiting, and on Redis none is held unacknowledged (the SQLite transport
    # hides a message for good when it delivers it).
    grace = 0 if settings.embedded_broker else 3600
    held = BrokerInspector(h.celery, settings).held_jobs(grace)
    assert held is not None and not set(dead) & held


def _only_this_tests_jobs(h: Harness) -> None:
    """Cancel every active job another test left in the session's PostgreSQL (a job store
    tests share): a waiting one would take part in these tests' picks, and have the turn."""
    with h.store.session() as s:
        s.execute(update(Job).where(Job.state.in_(ACTIVE)).values(state="cancelled"))


def _submit(h: Harness, tenant: str) -> str:
    """A job that fails at once in its pool process (its capture is gone): the order in which
    jobs start is what these tests look at, not training."""
    job = h.store.create(tenant, "reconstruct", {"preset": "test"}, capture_id=None)
    h.store.mark_dispatched(job.id)
    dispatch(h.celery, h.settings, job.id, "reconstruct")
    return job.id


def test_another_tenants_job_runs_before_a_tenants_queue(stack, tiny_capture: Path,
                                                          worker_factory):
    """A queues 3 jobs, then B 1, one worker: B's job runs second, not fourth (the queue's
    order); every job runs once, and a deferred message is neither lost nor an attempt. (The
    tenants are new: the session's PostgreSQL keeps other tests' picks.)"""
    env, settings = stack
    h = Harness(settings, tiny_capture)
    _only_this_tests_jobs(h)
    ta, tb = (f"{t}-{secrets.token_hex(3)}" for t in "ab")
    a = [_submit(h, ta) for _ in range(3)]
    b = _submit(h, tb)
    worker = worker_factory(env).start()
    jobs = {j: h.wait_state(j, ("succeeded", "failed")) for j in [*a, b]}
    assert {job.error["code"] for job in jobs.values()} == {"invalid_input"}
    assert [(job.attempts, len(job.runs)) for job in jobs.values()] == [(1, 1)] * 4
    order = sorted(jobs, key=lambda j: jobs[j].started_at)
    text = worker.log.read_text(errors="replace")
    assert order[:2] == [a[0], b], text[-3000:]
    assert f"tenant {tb} has the turn (0 on a worker; job {b} waiting)" in text


def test_a_message_runs_after_one_round_when_the_turn_has_none(stack, tiny_capture: Path,
                                                               worker_factory):
    """The tenant with the turn has a waiting job whose message is not in the queue (sent,
    then lost): another tenant's message goes round the queue once, then runs."""
    env, settings = stack
    h = Harness(settings, tiny_capture)
    _only_this_tests_jobs(h)
    tb = f"b-{secrets.token_hex(3)}"
    lost = h.store.create(tb, "reconstruct", {"preset": "test"}, capture_id=None)
    h.store.mark_dispatched(lost.id)  # and no message: lost with a worker
    a = _submit(h, f"a-{secrets.token_hex(3)}")
    worker = worker_factory(env).start()
    try:
        job = h.wait_state(a, ("succeeded", "failed"))
    finally:  # no waiting job left in the session's PostgreSQL for the next tests' picks
        h.store.request_cancel(lost.id, tb)
    assert job.attempts == 1 and job.error["code"] == "invalid_input", h.log(a)
    text = worker.log.read_text(errors="replace")
    assert text.count(f"job {a}: deferred") == 1, text[-3000:]


def _training(h: Harness, tenant: str, iterations: int) -> str:
    """A real training job of `tenant` on the harness's capture."""
    job = h.store.create(tenant, "reconstruct", {
        "preset": "test", "config": tiny_config(iterations), "checkpoint_every": 20},
        capture_id=h.capture_id)
    h.store.mark_dispatched(job.id)
    dispatch(h.celery, h.settings, job.id, "reconstruct")
    return job.id


def test_a_tenant_on_every_worker_gives_one_up(stack, tiny_capture: Path, worker_factory):
    """A's two long jobs hold both of a worker's pool processes when B submits: one of A's
    stops at a step and goes back to the queue (not an attempt lost), its pool process runs
    B's job, which ends while A's other job still runs, and A's job comes back with a new
    attempt to resume where it stopped."""
    env, settings = stack
    h = Harness(settings, tiny_capture)
    _only_this_tests_jobs(h)
    ta, tb = (f"{t}-{secrets.token_hex(3)}" for t in "ab")
    for tenant in (ta, tb):
        add_capture(h.store, h.blobs, tiny_capture, f"cap_{secrets.token_hex(4)}", tenant)
    worker = worker_factory({**env, "DGS_SHARE_AFTER_SECONDS": "1"}, "--concurrency=2").start()
    a = [_training(h, ta, 100_000) for _ in range(2)]
    try:
        wait_for(lambda: all(h.state(j) == "running" for j in a), 300, "A's jobs on both")
        b = _training(h, tb, 20)
        done = h.wait_state(b, ("succeeded", "failed"), timeout=300)
        text = worker.log.read_text(errors="replace")
        assert done.state == "succeeded", h.log(b) + text[-3000:]
        jobs = [h.store.get(j) for j in a]
        gave = [j for j in jobs if [r.get("outcome") for r in j.runs][:1] == ["released"]]
        assert len(gave) == 1, [j.runs for j in jobs]
        kept = next(j for j in jobs if j is not gave[0])
        assert (kept.state, len(kept.runs)) == ("running", 1)  # never stopped for B
        assert "back in the queue" in h.log(gave[0].id) and "fair share" in h.log(gave[0].id)
        # B's job ran in the pool process A's job left: no fresh process (torch imported) first.
        assert h.store.get(b).runs[0]["worker"] == gave[0].runs[0]["worker"], text[-3000:]
        assert f"job {b}: handed to this pool process after job {gave[0].id}" in text
        back = wait_for(lambda: (j if (j := h.store.get(gave[0].id)).attempts == 2
                                 and j.state == "running" else None), 300, "A's job back")
        assert back.redeliveries <= 1  # the release gave its attempt back
    finally:
        for job_id in a:
            h.store.request_cancel(job_id, ta)
        for job_id in a:
            h.wait_state(job_id, ("cancelled", "failed", "succeeded"), timeout=120)
