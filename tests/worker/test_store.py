"""The job store's lifecycle on SQLite and PostgreSQL: leases (one runner at a time), the
redelivery cap, takeover from a dead process, monotonic progress, cancel, retry, events, logs."""

from __future__ import annotations

import datetime as dt
import os
import subprocess
import sys
import threading

import pytest
from sqlalchemy import update

from worker.models import Job, utcnow
from worker.store import JobStore, Owner, progress_of


def _job(store: JobStore, tenant: str = "t1") -> str:
    return store.create(tenant, "reconstruct", {"preset": "test"}, capture_id=None).id


def test_one_lease_at_a_time(store: JobStore):
    job = _job(store)
    a, b = Owner.current(), Owner.current()  # two workers in this (live) process
    first = store.claim(job, a, 30, 3)
    assert first.status == "claimed" and first.job.attempts == 1 and first.job.state == "running"
    second = store.claim(job, b, 30, 3)
    assert second.status == "leased" and 28 < second.retry_in <= 30
    assert store.heartbeat(job, b, 30, {"fraction": 0.9}) == (False, False)  # not b's to write
    assert store.finish(job, b, "succeeded") is False
    assert store.get(job).state == "running" and store.get(job).fraction == 0.0


def test_racing_claims_have_one_winner(store: JobStore):
    job = _job(store)
    owners = [Owner.current() for _ in range(8)]
    results: list[str] = []
    barrier = threading.Barrier(len(owners))

    def claim(owner: Owner) -> None:
        barrier.wait()
        results.append(store.claim(job, owner, 30, 3).status)

    threads = [threading.Thread(target=claim, args=(o,)) for o in owners]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(results) == ["claimed"] + ["leased"] * 7
    assert store.get(job).attempts == 1


def test_expired_lease_is_taken_over_and_counted(store: JobStore):
    job = _job(store)
    a, b = Owner.current(), Owner.current()
    assert store.claim(job, a, 30, 3).status == "claimed"
    with store.session() as s:  # a's lease ran out (a stopped renewing it)
        s.execute(update(Job).where(Job.id == job).values(
            lease_expires_at=utcnow() - dt.timedelta(seconds=1)))
    claim = store.claim(job, b, 30, 3)
    assert claim.status == "claimed" and claim.job.attempts == 2
    assert store.heartbeat(job, a, 30) == (False, False)  # a learns it lost the job
    assert store.finish(job, a, "failed") is False


def test_lease_of_a_dead_process_is_taken_at_once(store: JobStore):
    proc = subprocess.run([sys.executable, "-c", "from worker.store import Owner; "
                           "print(Owner.current())"], capture_output=True, text=True, check=True,
                          env={**os.environ})
    dead = Owner.parse(proc.stdout.strip())
    assert dead is not None and dead.is_dead_here()
    assert not Owner.current().is_dead_here()
    job = _job(store)
    assert store.claim(job, dead, 600, 3).status == "claimed"
    claim = store.claim(job, Owner.current(), 600, 3)  # no waiting for the 600 s lease
    assert claim.status == "claimed" and claim.job.attempts == 2


def test_redelivery_cap_fails_the_job(store: JobStore):
    job = _job(store)
    for attempt in range(1, 3):
        assert store.claim(job, Owner.current(), 30, 2).job.attempts == attempt
        with store.session() as s:
            s.execute(update(Job).where(Job.id == job).values(lease_expires_at=utcnow()))
    claim = store.claim(job, Owner.current(), 30, 2)
    assert claim.status == "exhausted"
    failed = store.get(job)
    assert failed.state == "failed" and failed.error["code"] == "worker_lost"
    assert failed.error["retryable"] is True and "2 times" in failed.error["message"]
    assert store.retry(job, "t1").state == "queued"
    again = store.claim(job, Owner.current(), 30, 2).job
    assert (again.attempts, again.redeliveries) == (3, 1)  # the cap counts anew


def test_progress_never_goes_back_and_events_follow(store: JobStore):
    job = _job(store)
    owner = Owner.current()
    store.claim(job, owner, 30, 3)
    store.heartbeat(job, owner, 30, {"fraction": 0.4, "stage": "geometry", "iteration": 40,
                                     "iterations": 100, "frame": 1, "frames": 2, "eta_s": 12.0})
    store.heartbeat(job, owner, 30, {"fraction": 0.2, "stage": "appearance", "iteration": 20})
    now = store.get(job)
    assert now.fraction == 0.4 and now.iteration == 20 and now.stage == "appearance"
    assert progress_of(now)["fraction"] == 0.4
    store.heartbeat(job, owner, 30)  # lease only: no event
    assert store.finish(job, owner, "succeeded")
    events = store.events_after(job, 0)
    assert [e.kind for e in events] == ["state", "state", "progress", "progress", "state"]
    assert [e.data.get("state") for e in events if e.kind == "state"] == [
        "queued", "running", "succeeded"]
    assert [e.data["fraction"] for e in events if e.kind == "progress"] == [0.4, 0.4]
    assert events[-1].data["fraction"] == 1.0
    assert [e.id for e in store.events_after(job, events[2].id)] == [e.id for e in events[3:]]
    assert store.get(job).lease_owner is None


def test_cancel_queued_and_running(store: JobStore):
    queued = _job(store)
    assert store.request_cancel(queued, "other") is None  # another tenant: not found
    assert store.request_cancel(queued, "t1").state == "cancelled"
    assert store.claim(queued, Owner.current(), 30, 3).status == "terminal"

    running = _job(store)
    owner = Owner.current()
    store.claim(running, owner, 30, 3)
    job = store.request_cancel(running, "t1")
    assert job.state == "running" and job.cancel_requested
    assert store.heartbeat(running, owner, 30) == (True, True)  # the worker learns of it
    assert store.finish(running, owner, "cancelled")
    retried = store.retry(running, "t1")
    assert retried.state == "queued" and not retried.cancel_requested
    assert (retried.attempts, retried.redeliveries) == (1, 0)  # the cap counts anew


def test_cancel_reaches_a_job_between_two_workers(store: JobStore):
    job = _job(store)
    store.claim(job, Owner.current(), 30, 3)
    with store.session() as s:
        s.execute(update(Job).where(Job.id == job).values(lease_expires_at=utcnow()))
    store.request_cancel(job, "t1")
    claim = store.claim(job, Owner.current(), 30, 3)
    assert claim.status == "terminal" and store.get(job).state == "cancelled"


def test_retry_only_from_failed_or_cancelled(store: JobStore):
    job = _job(store)
    assert store.retry(job, "t1").state == "queued"  # unchanged
    owner = Owner.current()
    store.claim(job, owner, 30, 3)
    assert store.retry(job, "t1").state == "running"
    store.finish(job, owner, "succeeded")
    assert store.retry(job, "t1").state == "succeeded"
    assert store.retry(job, "t2") is None


def test_logs_page_by_offset(store: JobStore):
    job = _job(store)
    store.append_logs(job, [f"line {i}" for i in range(5)])
    store.append_logs(job, ["line 5"])
    store.append_logs(job, [])
    assert [(r.seq, r.line) for r in store.logs(job, 3, 2)] == [(3, "line 3"), (4, "line 4")]
    assert [r.seq for r in store.logs(job, 0, 100)] == list(range(6))
    assert store.logs(job, 6, 10) == []


def test_stranded_jobs_are_sent_once(store: JobStore):
    running, queued, fresh = _job(store), _job(store), _job(store)
    owner = Owner.current()
    store.claim(running, owner, 30, 3)
    past = utcnow() - dt.timedelta(hours=10)
    with store.session() as s:
        s.execute(update(Job).where(Job.id == running).values(lease_expires_at=utcnow()))
        s.execute(update(Job).where(Job.id == queued).values(dispatched_at=past))
    store.mark_dispatched(fresh)
    sent: list[str] = []
    assert sorted(store.redispatch_stranded(sent.append, requeue_after=3600, min_gap=60)) == \
        sorted([running, queued])
    # A second sweeper right after sends nothing (the first one just dispatched them).
    assert store.redispatch_stranded(sent.append, requeue_after=3600, min_gap=60) == {}
    assert sorted(sent) == sorted([running, queued])
    assert store.get(running).dispatches == 1


def test_a_queued_job_is_sent_again_only_when_its_message_is_gone(store: JobStore):
    waiting, lost, fresh, never = (_job(store) for _ in range(4))
    with store.session() as s:
        s.execute(update(Job).where(Job.id.in_([waiting, lost])).values(
            dispatched_at=utcnow() - dt.timedelta(hours=10)))
        s.execute(update(Job).where(Job.id == fresh).values(dispatched_at=utcnow()))
    held = {waiting}  # the broker still holds waiting's message; lost's and fresh's are gone
    why = store.stranded(held=held, grace=120)
    assert set(why) == {lost, never}  # fresh was sent 0 s ago: its worker may be claiming it
    assert "no longer in the broker" in why[lost] and "never sent" in why[never]
    assert set(store.stranded()) == {never}  # a pass that does not look into the broker
    aged = store.stranded(requeue_after=3600)  # a broker that cannot be inspected
    assert set(aged) == {waiting, lost, never} and "cannot be inspected" in aged[waiting]


def test_naive_datetimes_are_refused(store: JobStore):
    with pytest.raises(Exception, match="naive datetime"):
        store.create("t1", "reconstruct", {}, capture_id=None,
                     expires_at=dt.datetime(2030, 1, 1))
    job = store.create("t1", "reconstruct", {}, capture_id=None,
                       expires_at=dt.datetime(2030, 1, 1, tzinfo=dt.UTC))
    assert store.get(job.id).expires_at == dt.datetime(2030, 1, 1, tzinfo=dt.UTC)


def test_release_puts_the_job_back_for_another_worker(store: JobStore):
    job = _job(store)
    owner = Owner.current()
    store.mark_dispatched(job)
    store.claim(job, owner, 30, 3)
    assert store.release(job, Owner.current(), "not mine") is False  # only the holder may
    assert store.release(job, owner, "back in the queue: its worker shut down at step 7")
    back = store.get(job)
    assert (back.state, back.lease_owner, back.dispatched_at, back.redeliveries) == (
        "queued", None, None, 0)  # a run given back does not count towards the cap
    assert "step 7" in back.message
    sent: list[str] = []
    assert list(store.redispatch_stranded(sent.append, min_gap=60)) == [job]
    again = store.claim(job, Owner.current(), 30, 3).job
    assert (again.attempts, again.redeliveries) == (2, 1)
    assert [(r["attempt"], r.get("outcome")) for r in again.runs] == [(1, "released"), (2, None)]


def test_a_render_is_made_only_from_a_succeeded_job_of_its_tenant(store: JobStore):
    source, other = _job(store), _job(store, "t2")
    assert store.create_render("t1", source, "relight", {"envmap": "a"}) is None  # queued
    owner = Owner.current()
    for job in (source, other):
        store.claim(job, owner, 30, 3)
        store.finish(job, owner, "succeeded")
    assert store.create_render("t1", other, "relight", {"envmap": "a"}) is None
    assert store.create_render("t1", "job_missing", "relight", {"envmap": "a"}) is None
    render = store.create_render("t1", source, "relight", {"envmap": "a"})
    assert render.source_job_id == source and render.state == "queued"
    with store.session() as s:
        assert JobStore.dependents(s, source) == [render.id]
        assert JobStore.asset_users(s, "t1", "a") == [render.id]
        assert JobStore.asset_users(s, "t2", "a") == []
    model_user = store.create("t1", "reconstruct", {"config": {"normal_estimator": "m"}},
                              capture_id=None)
    with store.session() as s:
        assert JobStore.asset_users(s, "t1", "m") == [model_user.id]
    store.request_cancel(render.id, "t1")
    with store.session() as s:
        assert JobStore.dependents(s, source) == []
