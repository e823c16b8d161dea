"""Progress events of a running job: updates between two heartbeats are coalesced, but a frame
boundary never is. Deterministic: the heartbeat thread is never started, so every update of a
test lands in the single flush of `close()`, the worst case a loaded machine can produce."""

from __future__ import annotations

from pathlib import Path

import pytest

from core.pipeline import Progress
from worker.blobs import LocalBlobStore
from worker.pipelines import ReconstructParams
from worker.progress import JobLink
from worker.reconstruct_job import ReconstructJob
from worker.runner import Runner
from worker.settings import WorkerSettings
from worker.store import JobStore, Owner
from worker_harness import wait_for


@pytest.fixture
def claimed(tmp_path: Path, store_url: str):
    settings = WorkerSettings(data_dir=tmp_path / "data", database_url=store_url)
    store = JobStore(store_url)
    job = store.create("t1", "reconstruct", {}, capture_id=None)
    owner = Owner.current()
    claim = store.claim(job.id, owner, 60, 3)
    return settings, store, claim.job, owner


def _progress(store: JobStore, job_id: str) -> list[dict]:
    return [e.data for e in store.events_after(job_id, 0) if e.kind == "progress"]


def test_a_change_of_frame_is_never_coalesced(claimed):
    settings, store, job, owner = claimed
    link = JobLink(store, job, owner, settings)  # not started: nothing is written until close
    for frame in (1, 2, 3):
        for step in range(5):
            link.update(fraction=(frame - 1 + step / 5) / 3, frame=frame, frames=3,
                        iteration=step, stage="appearance")
    link.close()
    events = _progress(store, job.id)
    assert [e["frame"] for e in events] == [1, 2, 3, 3]  # each frame's first update, the last
    assert [e["iteration"] for e in events] == [0, 0, 0, 4]
    assert store.get(job.id).frame == 3


def test_milestones_are_events_of_their_own_and_steps_coalesce(claimed):
    settings, store, job, owner = claimed
    link = JobLink(store, job, owner, settings)
    link.update(fraction=0.1, frame=1, stage="appearance", milestone=True)
    for step in range(1, 50):
        link.update(fraction=0.1 + step / 100, frame=1, iteration=step)
    link.update(fraction=0.7, frame=1, stage="outputs", milestone=True)
    link.update(fraction=0.8, stage="publishing")
    link.close()
    events = _progress(store, job.id)
    assert [(e["stage"], e["iteration"]) for e in events] == [
        ("appearance", 0), ("outputs", 49), ("publishing", 49)]
    fractions = [e["fraction"] for e in events]
    assert fractions == sorted(fractions)


def test_every_frame_of_a_reconstruction_reaches_the_events(claimed, tmp_path: Path):
    """reconstruct_job's mapping of core's events: frame_start and frame_done of every frame
    are published even when all of them arrive between two heartbeats (issue 20: a loaded
    machine showed frames [1, 1, 3, 3, 3])."""
    settings, store, job, owner = claimed
    runner = Runner(settings, store, LocalBlobStore(settings.data_dir / "store"))
    link = JobLink(store, job, owner, settings)
    run = tmp_path / "run"
    run.mkdir()
    on_progress = ReconstructJob(runner, job, ReconstructParams(), link)._on_progress(run)
    for i, frame in enumerate(("000000", "000001", "000002")):
        common = dict(frame=frame, frame_index=i, frames=3, iterations=10, stage=2)
        on_progress(Progress("frame_start", step=0, **common))
        for step in range(1, 11):
            on_progress(Progress("step", step=step, loss=0.1, **common))
        on_progress(Progress("frame_done", step=10, path=str(run / "frames" / frame), **common))
    link.close()
    events = _progress(store, job.id)
    frames = [e["frame"] for e in events]
    assert frames == [1, 1, 2, 2, 3, 3], frames
    assert [e["stage"] for e in events][1::2] == ["outputs"] * 3  # each frame_done
    assert [e["iteration"] for e in events][0::2] == [0, 0, 0]  # each frame_start


def test_a_cancel_and_a_waiting_tenant_are_seen_between_heartbeats(claimed):
    """A running job looks for a cancel and for another tenant's turn every `watch_seconds`,
    not only at its heartbeat: with no heartbeat in the test's time, both still stop it."""
    settings, store, job, owner = claimed
    settings = settings.model_copy(update={"heartbeat_seconds": 3600.0, "watch_seconds": 0.05,
                                           "share_after_seconds": 0.01})
    link = JobLink(store, job, owner, settings).start()
    try:
        store.request_cancel(job.id, "t1")
        wait_for(link.should_stop, 300, "the cancel to be seen")
        assert link.cancelled and not link.yielding
    finally:
        link.close()

    first, last = (store.create("t1", "reconstruct", {}, capture_id=None) for _ in range(2))
    store.claim(first.id, Owner.current(), 60, 3)
    claim = store.claim(last.id, owner, 60, 3)  # t1's job claimed last is the one asked
    store.mark_dispatched(store.create("t2", "reconstruct", {}, capture_id=None).id)
    link = JobLink(store, claim.job, owner, settings).start()
    try:
        wait_for(link.should_stop, 300, "t2's turn to be seen")
        assert link.yielding and not link.cancelled
        assert store.get(last.id).yield_asked_at is not None
    finally:
        link.close()
