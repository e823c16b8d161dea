"""A job's folder in a worker's scratch space (<scratch>/jobs/<id>/: run directory, relight
work) lives while a worker of this scratch space runs the job. A worker killed outright (SIGKILL,
a lost machine) leaves its folder behind; `stale_job_folders` finds such folders and
`clean_job_folders` deletes them: the job has ended (or is gone), or another worker resumed it
with a scratch space of its own (its state comes from the store; the folder here is stale).

Whoever claims a job writes its owner into the folder (`mark`): a worker resuming the job on
the same scratch space (several workers on one machine or volume) overwrites it, so a folder
whose mark names someone else than the job's live lease holder was left by a worker that is
no longer the job's.
"""

from __future__ import annotations

import datetime as dt
import logging
import shutil
from pathlib import Path

from sqlalchemy import select

from worker.models import Job, utcnow
from worker.store import TERMINAL, JobStore, Owner

__all__ = ["MARK", "clean_job_folders", "job_folder", "mark", "stale_job_folders"]

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
