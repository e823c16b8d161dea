"""Scratch folders of jobs (<scratch>/jobs/<id>/): which ones no worker of this scratch space
will use again, and what a job's failure tells its client about this machine's folders."""

from __future__ import annotations

import datetime as dt
import os
import shutil
from pathlib import Path

import pytest
from sqlalchemy import update
from worker_harness import add_capture

from worker.blobs import LocalBlobStore
from worker.models import Capture, Job, utcnow
from worker.runner import Runner
from worker.scratch import (MARK, capture_folder, clean_capture_folders, clean_job_folders,
                            hold_capture, mark, stale_job_folders)
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


def _cached(scratch: Path, capture_id: str, fetched: list[str]):
    """Fetch a capture into `scratch` as a job does (a file and the complete mark), held."""
    def fetch(folder: Path) -> None:
        (folder / "capture.json").write_text("{}")
        fetched.append(capture_id)
    return hold_capture(capture_folder(scratch, capture_id), fetch)


def _aged(scratch: Path, capture_id: str, seconds: float) -> None:
    mark_file = capture_folder(scratch, capture_id) / ".complete"
    then = mark_file.stat().st_mtime - seconds
    os.utime(mark_file, (then, then))


def test_a_cached_capture_stays_while_a_job_holds_or_needs_it(store: JobStore, tmp_path: Path):
    """A capture fetched from S3 into a worker's scratch space is deleted when nobody holds it
    and no active job needs it: at once when its capture is gone, else once unused for the
    idle time. A second job on it reads the copy (no fetch) and marks it used."""
    scratch, fetched = tmp_path / "work", []
    with store.session() as s:
        s.add(Capture(id="cap_kept", tenant="t1", format="canonical", state="ready"))
    held = _cached(scratch, "cap_kept", fetched)
    _aged(scratch, "cap_kept", 7200)
    assert clean_capture_folders(store, scratch, 3600) == []  # a running job holds it
    held.close()
    job = store.create("t1", "reconstruct", {}, capture_id="cap_kept")
    assert clean_capture_folders(store, scratch, 3600) == []  # a queued job will need it
    store.request_cancel(job.id, "t1")
    _cached(scratch, "cap_kept", fetched).close()  # used again: no fetch, marked used now
    assert fetched == ["cap_kept"]
    assert clean_capture_folders(store, scratch, 3600) == []  # used a moment ago
    _aged(scratch, "cap_kept", 7200)
    assert clean_capture_folders(store, scratch, 3600) == ["cap_kept"]
    assert not capture_folder(scratch, "cap_kept").exists()

    _cached(scratch, "cap_gone", fetched).close()  # no row: the capture was deleted
    assert clean_capture_folders(store, scratch, 3600) == ["cap_gone"]


def test_a_job_that_waited_on_a_cleaner_fetches_the_capture_again(tmp_path: Path):
    """A job that reaches a cached capture while the cleaner deletes it waits for the cleaner,
    then finds the copy gone and fetches it again, into a folder of its own (whichever comes
    first, the outcome is the same)."""
    import fcntl
    import threading

    scratch, fetched = tmp_path / "work", []
    _cached(scratch, "cap_a", fetched).close()
    folder = capture_folder(scratch, "cap_a")
    cleaner = open(folder / ".held", "a")
    fcntl.flock(cleaner, fcntl.LOCK_EX)
    out: list = []
    job = threading.Thread(target=lambda: out.append(_cached(scratch, "cap_a", fetched)))
    job.start()
    (folder / ".complete").unlink()  # as the cleaner does: the mark first, then the rest
    shutil.rmtree(folder, ignore_errors=True)  # the job may be making a folder anew
    cleaner.close()
    job.join(60)
    assert not job.is_alive() and out, "the job still waits"
    assert fetched == ["cap_a", "cap_a"]
    assert (folder / "capture.json").is_file() and (folder / ".complete").is_file()
    out[0].close()


def test_two_jobs_that_hold_a_capture_unfetched_both_go_on(tmp_path: Path, monkeypatch):
    """Two jobs reach a capture not yet fetched at once and both hold it before either
    fetches (a barrier after each one's shared lock makes it so): one fetches, the other waits
    for that fetch only and reads it. The fetch used to want the holders' lock exclusively:
    it waited for the other job's whole run (CI hung on it)."""
    import fcntl
    import threading

    from worker import scratch as scratch_module

    both, locked = threading.Barrier(2, timeout=60), scratch_module._locked

    def held_by_both(*args):
        f = locked(*args)
        if args[-1] == fcntl.LOCK_SH and not getattr(threading.current_thread(), "met", False):
            threading.current_thread().met = True
            both.wait()
        return f

    monkeypatch.setattr(scratch_module, "_locked", held_by_both)
    scratch, fetched, out = tmp_path / "work", [], []
    jobs = [threading.Thread(target=lambda: out.append(_cached(scratch, "cap_b", fetched)),
                             daemon=True) for _ in range(2)]
    for job in jobs:
        job.start()
    for job in jobs:
        job.join(60)
    try:
        assert not any(job.is_alive() for job in jobs), "a fetch waits for the other job to end"
        assert len(out) == 2 and fetched == ["cap_b"]
    finally:
        for f in out:
            f.close()
