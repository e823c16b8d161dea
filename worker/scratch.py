"""A worker's scratch space: job folders, and the captures fetched from an S3 store.

A job's folder in a worker's scratch space (<scratch>/jobs/<id>/: run directory, relight
work) lives while a worker of this scratch space runs the job. A worker killed outright (SIGKILL,
a lost machine) leaves its folder behind; `stale_job_folders` finds such folders and
`clean_job_folders` deletes them: the job has ended (or is gone), or another worker resumed it
with a scratch space of its own (its state comes from the store; the folder here is stale).

Whoever claims a job writes its owner into the folder (`mark`): a worker resuming the job on
the same scratch space (several workers on one machine or volume) overwrites it, so a folder
whose mark names someone else than the job's live lease holder was left by a worker that is
no longer the job's.

A capture fetched from the artifact store (<scratch>/captures/<id>/, `worker.runner`) is held by
every job that uses it: a shared lock on its `.held` file for the job's whole run. One process
fetches it, holding `.fetching` exclusively, while the others wait on that lock (never on a
holder: a job that waited for `.held` exclusively would wait for every other job on the capture
to end). `clean_capture_folders` deletes one that nobody holds and no active job will need once
its capture is gone (deleted or expired: a tenant's deleted data does not stay on the workers'
disks) or nobody used it for a while.
"""

from __future__ import annotations

import datetime as dt
import fcntl
import logging
import os
import shutil
import time
from pathlib import Path
from typing import IO

from sqlalchemy import select

from worker.models import Capture, Job, utcnow
from worker.store import ACTIVE, TERMINAL, JobStore, Owner

__all__ = ["MARK", "capture_folder", "clean_capture_folders", "clean_job_folders", "hold_capture",
           "job_folder", "mark", "stale_job_folders"]

log = logging.getLogger("dgs.sweeper")
MARK = ".owner"
SETTLE = dt.timedelta(seconds=60)
"""A claim younger than this may not have written its mark yet."""


def job_folder(scratch: Path, job_id: str) -> Path:
    return scratch / "jobs" / job_id


def mark(scratch: Path, job_id: str, owner: Owner) -> None:
    """Record that `owner` (who just claimed the job) works in this scratch space."""
    folder = job_folder(scratch, job_id)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / MARK).write_text(str(owner))


def stale_job_folders(store: JobStore, scratch: Path) -> dict[Path, str]:
    """{folder: why} of the job folders under `scratch` that no worker of it will use."""
    root = scratch / "jobs"
    folders = {p.name: p for p in root.iterdir() if p.is_dir()} if root.is_dir() else {}
    if not folders:
        return {}
    now = utcnow()
    out: dict[Path, str] = {}
    with store.session(write=False) as s:
        rows = {r.id: r for r in s.execute(
            select(Job.id, Job.state, Job.lease_owner, Job.lease_expires_at, Job.run_started_at)
            .where(Job.id.in_(list(folders))))}
    for job_id, folder in folders.items():
        row = rows.get(job_id)
        if row is None or row.state in TERMINAL:
            out[folder] = "the job has ended" if row is not None else "the job was deleted"
            continue
        try:
            marked = (folder / MARK).read_text()
        except OSError:
            continue  # a folder of a worker from before marks, or being made: leave it
        live = row.lease_owner is not None and row.lease_expires_at is not None and \
            row.lease_expires_at > now
        settled = row.run_started_at is not None and row.run_started_at < now - SETTLE
        if live and settled and marked != row.lease_owner:
            out[folder] = f"the job was resumed by {row.lease_owner} with a scratch space of " \
                          "its own"
    return out


def clean_job_folders(store: JobStore, scratch: Path) -> list[str]:
    """Delete `stale_job_folders` (each logged); returns the job ids."""
    done = []
    for folder, why in stale_job_folders(store, scratch).items():
        shutil.rmtree(folder, ignore_errors=True)
        log.info("job %s: removed its scratch folder %s (%s)", folder.name, folder, why)
        done.append(folder.name)
    return done


HELD, FETCHING, COMPLETE, CAPTURES = ".held", ".fetching", ".complete", "captures"


def capture_folder(scratch: Path, capture_id: str) -> Path:
    return scratch / CAPTURES / capture_id


def _locked(path: Path, how: int) -> IO[str]:
    """`path` open and flocked `how`, on the file that is at that path now (a cleaner may have
    deleted its folder while this process waited: then again, on a new one)."""
    while True:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            f = open(path, "a")
        except (FileExistsError, FileNotFoundError):  # the cleaner removed it meanwhile
            continue
        try:
            fcntl.flock(f, how)
            if os.fstat(f.fileno()).st_ino == os.stat(path).st_ino:
                return f
        except FileNotFoundError:
            pass
        except BaseException:
            f.close()
            raise
        f.close()


def hold_capture(folder: Path, fetch) -> IO[str]:
    """Hold the capture cached in `folder` for a job: fetched first by `fetch(folder)` unless
    complete (one process fetches, holding `.fetching`; the others wait for that lock and read
    what it fetched), then held until the returned file is closed, so no cleaner deletes it
    under the job. Each hold marks the capture used now."""
    held = _locked(folder / HELD, fcntl.LOCK_SH)  # no cleaner deletes the folder from here on
    try:
        if not (folder / COMPLETE).is_file():
            with open(folder / FETCHING, "a") as fetching:
                fcntl.flock(fetching, fcntl.LOCK_EX)
                if not (folder / COMPLETE).is_file():
                    fetch(folder)
                    (folder / COMPLETE).touch()
        os.utime(folder / COMPLETE)
        return held
    except BaseException:
        held.close()
        raise


def clean_capture_folders(store: JobStore, scratch: Path, idle_seconds: float) -> list[str]:
    """Delete the captures cached under `scratch` that no job holds and no active job will
    need, at once when the capture is gone from the store, else once unused for `idle_seconds`
    (each logged); returns the capture ids."""
    root = scratch / CAPTURES
    folders = {p.name: p for p in root.iterdir() if p.is_dir()} if root.is_dir() else {}
    if not folders:
        return []
    with store.session(write=False) as s:
        needed = set(s.scalars(select(Job.capture_id).where(
            Job.state.in_(ACTIVE), Job.capture_id.in_(list(folders)))))
        known = set(s.scalars(select(Capture.id).where(Capture.id.in_(list(folders)))))
    done = []
    for capture_id, folder in folders.items():
        if capture_id in needed:
            continue
        try:
            f = open(folder / HELD, "a")
        except OSError:
            continue
        with f:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:  # a job holds it, or is fetching it
                continue
            if capture_id in known:
                marker = folder / COMPLETE if (folder / COMPLETE).is_file() else folder / HELD
                if time.time() - marker.stat().st_mtime < idle_seconds:
                    continue
                why = f"unused for {idle_seconds / 3600:g} h"
            else:
                why = "the capture was deleted"
            (folder / COMPLETE).unlink(missing_ok=True)  # a waiting job fetches it again
            shutil.rmtree(folder, ignore_errors=True)
        log.info("capture %s: removed its copy in this scratch space (%s)", capture_id, why)
        done.append(capture_id)
    return done
