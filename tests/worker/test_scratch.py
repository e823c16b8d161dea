"""Scratch folders of jobs (<scratch>/jobs/<id>/): which ones no worker of this scratch space
will use again, and what a job's failure tells its client about this machine's folders."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest
from sqlalchemy import update
from worker_harness import add_capture

from worker.blobs import LocalBlobStore
from worker.models import Job, utcnow
from worker.runner import Runner
from worker.scratch import MARK, clean_job_folders, mark, stale_job_folders
from worker.settings import WorkerSettings
from worker.store import JobStore, Owner


@pytest.fixture
def store(store_url: str) -> JobStore:
    return JobStore(store_url)


def _claimed(store: JobStore, owner: Owner, settled: bool = True) -> str:
    job = store.create("t1", "reconstruct", {}, capture_id=None).id
    store.claim(job, owner, 60, 3)
    if settled:  # claimed long enough ago that its worker has marked its folder
        with store.session() as s:
            s.execute(update(Job).where(Job.id == job).values(
                run_started_at=utcnow() - dt.timedelta(minutes=5)))
    return job


def test_stale_job_folders(store: JobStore, tmp_path: Path):
    scratch = tmp_path / "work"
    me, other = Owner.current(), Owner("elsewhere", 1, "1", "abcd")
    ended = _claimed(store, me)
    store.finish(ended, me, "cancelled")
    mine = _claimed(store, me)  # running here
    resumed = _claimed(store, other)  # resumed by a worker with its own scratch space
    fresh = _claimed(store, other, settled=False)  # its new worker may be marking it now
    queued = store.create("t1", "reconstruct", {}, capture_id=None).id
    for job in (ended, mine, resumed, fresh, queued):
        mark(scratch, job, me)
    (scratch / "jobs" / "job_deleted").mkdir()
    unmarked = _claimed(store, other)
    (scratch / "jobs" / unmarked).mkdir()  # a folder of a worker that wrote no mark
    stale = {p.name: why for p, why in stale_job_folders(store, scratch).items()}
    assert set(stale) == {ended, resumed, "job_deleted"}
    assert "ended" in stale[ended] and "deleted" in stale["job_deleted"]
    assert str(other) in stale[resumed]
    assert sorted(clean_job_folders(store, scratch)) == sorted(stale)
    assert sorted(p.name for p in (scratch / "jobs").iterdir()) == sorted(
        [mine, fresh, queued, unmarked])
    assert (scratch / "jobs" / mine / MARK).read_text() == str(me)


def test_a_failure_names_capture_files_not_server_folders(store: JobStore, store_url: str,
                                                           tiny_capture: Path, tmp_path: Path):
    settings = WorkerSettings(data_dir=tmp_path / "data", database_url=store_url)
    blobs = LocalBlobStore(settings.data_dir / "store")
    cap = add_capture(store, blobs, tiny_capture)
    image = blobs.local_path(f"captures/{cap}/images/000000/cam01.png")
    image.write_bytes(image.read_bytes()[:100])  # damaged in the store after its commit
    job = store.create("t1", "reconstruct", {"preset": "test"}, capture_id=cap)
    assert Runner(settings, store, blobs).run(job.id).status == "failed"
    after = store.get(job.id)
    assert after.error["code"] == "invalid_input"
    assert "images/000000/cam01.png" in after.error["message"], after.error
    logs = "\n".join(r.line for r in store.logs(job.id, 0, 1000))
    for text in (after.error["message"], after.message, logs):
        assert str(settings.data_dir) not in text and str(tmp_path) not in text
    assert not (settings.scratch / "jobs" / job.id).exists()  # an ended job leaves no folder
