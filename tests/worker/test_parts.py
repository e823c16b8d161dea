"""A sequence job run as parts (docs/design.md 4.4), in the job store (how a job is split is
core.config.independent_groups, tests/core/test_resolved.py): one lease per part (a duplicate
delivery does nothing), the parent waiting for its parts and then for its assembly, a failed
part retried alone, a cancel reaching every part."""

from __future__ import annotations

from dataclasses import replace

import pytest

from worker.parts import overall_progress
from worker.store import JobStore, Owner

FRAMES = [f"{i:06d}" for i in range(7)]
GROUPS = [FRAMES[0:3], FRAMES[3:6], FRAMES[6:7]]


def make(store: JobStore):
    return store.create_parted("t1", "reconstruct", {"preset": "test", "gop": 3}, GROUPS,
                               capture_id=None)


def claim(store: JobStore, job_id: str, owner: Owner | None = None):
    return store.claim(job_id, owner or Owner.current(), lease_seconds=60, max_attempts=3)


def states(store: JobStore, parent_id: str) -> list[str]:
    return [p.state for p in store.parts(parent_id)]


def test_each_part_has_its_own_lease_and_the_parent_waits_for_them(store: JobStore):
    parent, parts = make(store)
    assert [p.part_frames for p in parts] == GROUPS and parent.parts == 3
    # The parent is not run (nor re-sent by a sweeper) while its parts are to run.
    assert claim(store, parent.id).status == "waiting"
    assert parent.id not in store.stranded()
    first = Owner.current()
    assert claim(store, parts[0].id, first).status == "claimed"
    assert store.get(parent.id).state == "running"
    # Exactly once per part: a duplicate delivery finds the lease held and does nothing.
    other = replace(first, token="0ther")
    assert claim(store, parts[0].id, other).status == "leased"
    assert claim(store, parts[1].id, other).status == "claimed"  # two parts at once
    for part, owner in ((parts[0], first), (parts[1], other)):
        assert store.finish(part.id, owner, "succeeded")
    assert store.get(parent.id).state == "running"  # part 2 is still queued
    assert claim(store, parts[2].id).status == "claimed"
    assert store.finish(parts[2].id, Owner.parse(store.get(parts[2].id).lease_owner),
                        "succeeded")
    # Every part done: the parent waits for its assembly, unleased and unsent.
    parent = store.get(parent.id)
    assert (parent.state, parent.stage, parent.lease_owner) == ("running", "assembling", None)
    assert parent.id in store.stranded()
    assert claim(store, parent.id).status == "claimed"
    # A part that has ended is never run again.
    assert claim(store, parts[0].id).status == "terminal"


def test_a_failed_part_fails_the_job_and_a_retry_runs_it_alone(store: JobStore):
    parent, parts = make(store)
    owner = Owner.current()
    for part in parts:
        assert claim(store, part.id, owner).status == "claimed"
    assert store.finish(parts[0].id, owner, "succeeded")
    assert store.finish(parts[1].id, owner, "failed",
                        {"code": "internal", "retryable": True, "message": "boom"})
    assert store.get(parent.id).state == "running"  # part 2 still runs
    assert store.finish(parts[2].id, owner, "succeeded")
    failed = store.get(parent.id)
    assert failed.state == "failed" and failed.error["code"] == "internal"
    assert "part 1 (frames 000003..000005): boom" in failed.error["message"]
    job = store.retry(parent.id, "t1")
    assert job.state == "queued"
    assert states(store, parent.id) == ["succeeded", "queued", "succeeded"]
    assert store.to_dispatch(parent.id) == [parts[1].id]
    assert claim(store, parts[1].id).status == "claimed"
    assert store.finish(parts[1].id, Owner.parse(store.get(parts[1].id).lease_owner),
                        "succeeded")
    assert store.get(parent.id).stage == "assembling"


def test_a_cancel_stops_every_part_and_leaves_none_queued(store: JobStore):
    parent, parts = make(store)
    owner = Owner.current()
    assert claim(store, parts[0].id, owner).status == "claimed"
    store.request_cancel(parent.id, "t1")
    assert states(store, parent.id) == ["running", "cancelled", "cancelled"]
    # The running part's heartbeat sees the cancel (its worker stops at the next step).
    assert store.heartbeat(parts[0].id, owner, 60, {"fraction": 0.5}) == (True, True)
    assert store.get(parent.id).state == "running"
    assert store.finish(parts[0].id, owner, "cancelled")
    assert store.get(parent.id).state == "cancelled"
    assert states(store, parent.id) == ["cancelled"] * 3
    store.retry(parent.id, "t1")
    assert sorted(store.to_dispatch(parent.id)) == sorted(p.id for p in parts)


def test_a_cancel_of_a_job_whose_parts_are_all_queued_ends_it_at_once(store: JobStore):
    parent, _ = make(store)
    assert store.request_cancel(parent.id, "t1").state == "cancelled"
    assert states(store, parent.id) == ["cancelled"] * 3
    assert not store.stranded()


def test_progress_is_over_the_parts_and_their_events_reach_the_parent(store: JobStore):
    parent, parts = make(store)
    owner = Owner.current()
    assert claim(store, parts[0].id, owner).status == "claimed"
    assert store.heartbeat(parts[0].id, owner, 60, {"fraction": 0.5, "frame": 2})[0]
    with store.session(write=False) as s:
        rows = [store.get(p.id) for p in parts]
        job = s.get(type(rows[0]), parent.id)
        overall = overall_progress(job, rows)
    # 1.5 of 7 frames done (weighted by each part's frames), 1% kept for the assembly.
    assert overall["fraction"] == pytest.approx(0.5 * 3 / 7 * 0.99)
    assert overall["frames"] == 7 and overall["stage"] == "parts"
    part_events = [e.data for e in store.events_after(parent.id, 0) if e.kind == "part"]
    assert {"state", "progress"} <= {e["event"] for e in part_events}
    assert all(e["part"] == 0 for e in part_events)


def test_a_part_keeps_the_worker_that_ran_it_and_each_attempts(store: JobStore):
    """The lease is cleared when a part ends; the part keeps who ran it (issue 32): its last
    worker, and every run with how it ended (lost with its worker, released, finished)."""
    _, parts = make(store)
    lost, gone, last = (Owner(f"gpu-{n}", 100 + i, "?", "t") for i, n in enumerate("abc"))
    assert store.claim(parts[0].id, lost, lease_seconds=0, max_attempts=5).status == "claimed"
    assert store.claim(parts[0].id, gone, lease_seconds=60, max_attempts=5).status == "claimed"
    assert store.release(parts[0].id, gone, "shutting down")
    assert claim(store, parts[0].id, last).status == "claimed"
    assert store.finish(parts[0].id, last, "succeeded")
    part = store.parts(parts[0].parent_id)[0]
    assert part.lease_owner is None and part.worker == "gpu-c/102"
    assert [(r["worker"], r["outcome"]) for r in part.runs] == [
        ("gpu-a/100", "lost"), ("gpu-b/101", "released"), ("gpu-c/102", "succeeded")]
    assert all(r["started_at"] <= r["ended_at"] for r in part.runs)
    # The parent's stream says so too: the part's state events name its worker.
    events = [e.data for e in store.events_after(part.parent_id, 0) if e.kind == "part"
              and e.data.get("event") == "state" and "runs" in e.data]
    assert events[-1]["state"] == "succeeded" and events[-1]["worker"] == "gpu-c/102"
    assert [r["worker"] for r in events[-1]["runs"]] == ["gpu-a/100", "gpu-b/101", "gpu-c/102"]


def test_attempt_numbers_go_up_across_a_retry(store: JobStore):
    """A part cancelled while running and retried runs as attempt 2, not as attempt 1 again
    (issue 42: its runs read (1, cancelled) then (1, succeeded)); the redelivery cap still
    counts from the retry, and the assembly's attempts go up the same way."""
    parent, parts = make(store)
    owner = Owner.current()
    assert claim(store, parts[0].id, owner).status == "claimed"
    store.request_cancel(parent.id, "t1")
    assert store.finish(parts[0].id, owner, "cancelled")
    assert store.get(parent.id).state == "cancelled"
    store.retry(parent.id, "t1")
    again = claim(store, parts[0].id, owner).job
    assert (again.attempts, again.redeliveries) == (2, 1)
    assert store.finish(parts[0].id, owner, "succeeded")
    part = store.parts(parent.id)[0]
    assert [(r["attempt"], r["outcome"]) for r in part.runs] == [(1, "cancelled"),
                                                                 (2, "succeeded")]
    for other in parts[1:]:
        claim(store, other.id, owner)
        assert store.finish(other.id, owner, "succeeded")
    assembly = claim(store, parent.id, owner).job  # every part done: the assembly
    assert store.finish(parent.id, owner, "failed", {"code": "internal"}, "boom")
    store.retry(parent.id, "t1")  # only the assembly is left to run
    assert claim(store, parent.id, owner).job.attempts == assembly.attempts + 1
    runs = store.get(parent.id).runs
    assert [r["attempt"] for r in runs] == [1, 2] and runs[0]["outcome"] == "failed"


def test_a_job_retried_runs_its_next_attempt(store: JobStore):
    job = store.create("t1", "reconstruct", {"preset": "test"}, capture_id=None)
    owner = Owner.current()
    for outcome in ("cancelled", "failed", "succeeded"):
        assert claim(store, job.id, owner).status == "claimed"
        assert store.finish(job.id, owner, outcome)
        if outcome != "succeeded":
            assert store.retry(job.id, "t1").state == "queued"
    done = store.get(job.id)
    assert done.attempts == 3 and done.redeliveries == 1
    assert [(r["attempt"], r["outcome"]) for r in done.runs] == [
        (1, "cancelled"), (2, "failed"), (3, "succeeded")]
    state = [e.data for e in store.events_after(job.id, 0) if e.kind == "state"][-1]
    assert state["attempts"] == 3
