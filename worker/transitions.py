"""A job's state transitions, applied to its rows inside a transaction the caller holds
(`worker.store.JobStore` opens it): the job states, the events every change appends, ending a
job and what ending one of its parts does to a job run as parts (docs/design.md 4.4), and the
other changes particular to parted jobs (making them, a part's claim, cancel and retry). Each
function takes the open `Session`; none commits.

`worker.parts` holds the decisions about parts that need no database (how the parts' states
roll up, the overall progress); this module applies them to the rows.
"""

from __future__ import annotations

import datetime as dt
import secrets
from typing import Any, Literal

from sqlalchemy import select
from sqlalchemy.orm import Session

from worker.idempotency import Idempotency, remember
from worker.lease import run_ended
from worker.models import Job, JobEvent, utcnow
from worker.parts import ASSEMBLY_SHARE, failed_error, part_event, parts_of, roll_up

__all__ = ["ACTIVE", "TERMINAL", "JobState", "cancel_parts", "create_parted", "event", "finish",
           "lock", "new_id", "part_claimed", "progress_of", "retry_parts", "state_event",
           "to_dispatch"]

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
ACTIVE = ("queued", "running")
"""The states of a job that is not over (it holds its capture, its sources, a worker)."""
TERMINAL = ("succeeded", "failed", "cancelled")


def new_id(prefix: str) -> str:
    """An unguessable id like `job_3f9c0a1b2d4e5f60a7b8` (80 random bits)."""
    return f"{prefix}_{secrets.token_hex(10)}"


def progress_of(job: Job) -> dict[str, Any]:
    """The progress object of the API (docs/design.md 3.5)."""
    return {"stage": job.stage, "frame": job.frame, "frames": job.frames,
            "iteration": job.iteration, "iterations": job.iterations,
            "fraction": round(job.fraction, 6), "eta_s": job.eta_s, "message": job.message}


def event(s: Session, job_id: str, kind: str, data: dict[str, Any]) -> None:
    s.add(JobEvent(job_id=job_id, kind=kind, data=data))


def state_event(s: Session, job: Job) -> None:
    """The job's state event (and, for a part, its parent's `part` event saying so)."""
    data = {"state": job.state, "error": job.error, "attempts": job.attempts,
            "worker": job.worker, "runs": job.runs or [], **progress_of(job)}
    event(s, job.id, "state", data)
    if job.parent_id is not None:  # the parent's stream says what its parts do
        part_event(s, job, "state", data)


def lock(s: Session, job_id: str) -> Job | None:
    """The job's row locked; a part's parent is locked first, so that every transaction that
    locks both (a part's claim or end, a cancel of its job) takes them in the same order and
    none waits for another in a cycle (PostgreSQL)."""
    parent_id = s.scalar(select(Job.parent_id).where(Job.id == job_id))
    if parent_id is not None:
        s.get(Job, parent_id, with_for_update=True)
    return s.get(Job, job_id, with_for_update=True)


def finish(s: Session, job: Job, state: JobState, error: dict[str, Any] | None,
           message: str) -> None:
    """End the job; a part's end may end its parent or make it wait for its assembly."""
    job.state, job.error, job.finished_at = state, error, utcnow()
    run_ended(job, state, job.finished_at)
    job.lease_owner = job.lease_expires_at = None
    job.eta_s = None
    job.stage = state
    if message:
        job.message = message[:512]
    if state == "succeeded":
        job.fraction = 1.0
    state_event(s, job)
    if job.parent_id is not None:
        _roll_up(s, job)


# -- jobs run as parts ----------------------------------------------------------------------
def create_parted(s: Session, tenant: str, pipeline: str, params: dict[str, Any],
                  groups: list[list[str]], *,
                  capture_id: str | None, name: str = "",
                  expires_at: dt.datetime | None = None,
                  idempotency: Idempotency | None = None,
                  resolved_run: dict[str, Any] | None = None) -> tuple[Job, list[Job]]:
    """A sequence job and its parts (one per group of `groups`), all queued; the caller
    dispatches the parts (the parent itself is dispatched when they have succeeded).
    `idempotency`, `resolved_run`: as `JobStore.create` (the key names the parent; every
    part runs the same run)."""
    parent = Job(id=new_id("job"), tenant=tenant, capture_id=capture_id, pipeline=pipeline,
                 params=params, name=name, state="queued", stage="queued",
                 expires_at=expires_at, parts=len(groups), frames=sum(map(len, groups)),
                 resolved_run=resolved_run)
    s.add(parent)
    s.flush()
    remember(s, idempotency, parent.id)
    parts = [Job(id=new_id("job"), tenant=tenant, capture_id=capture_id, pipeline=pipeline,
                 params=params, name=name, state="queued", stage="queued", parent_id=parent.id,
                 part_index=i, part_frames=frames, frames=len(frames),
                 resolved_run=resolved_run)
             for i, frames in enumerate(groups)]
    s.add_all(parts)
    s.flush()
    state_event(s, parent)
    return parent, parts


def _roll_up(s: Session, part: Job) -> None:
    """After a part ended: end the parent when none of its parts is left to run, or make it
    wait for its assembly when every part succeeded."""
    parent = s.get(Job, part.parent_id, with_for_update=True)
    if parent is None or parent.state not in ("queued", "running"):
        return
    s.flush()
    parts = parts_of(s, parent.id)
    outcome = roll_up(s, parent, parts)
    if outcome == "assemble":
        parent.state, parent.stage, parent.dispatched_at = "running", "assembling", None
        parent.lease_owner = parent.lease_expires_at = None
        parent.fraction = max(parent.fraction, 1 - ASSEMBLY_SHARE)
        parent.started_at = parent.started_at or utcnow()
        state_event(s, parent)
    elif outcome == "failed":
        finish(s, parent, "failed", failed_error(parts), "")
    elif outcome == "cancelled":
        finish(s, parent, "cancelled", None, "cancelled; retry runs the cancelled parts again")


def part_claimed(s: Session, part: Job) -> None:
    """A part started: its parent is running from then on."""
    parent = s.get(Job, part.parent_id, with_for_update=True)
    if parent is not None and parent.state == "queued":
        parent.state, parent.stage = "running", "parts"
        parent.started_at = parent.started_at or utcnow()
        state_event(s, parent)


def cancel_parts(s: Session, parent: Job) -> None:
    """Cancel every part: a queued one at once, a running one at its next step."""
    for part in parts_of(s, parent.id, lock=True):
        if part.state == "queued" and part.lease_owner is None:
            part.state, part.stage, part.finished_at = "cancelled", "cancelled", utcnow()
            part.eta_s = None
            state_event(s, part)
        elif part.state in ("queued", "running"):
            part.cancel_requested = True
            part_event(s, part, "state", {"state": part.state, "cancel_requested": True})
    s.flush()
    if parent.lease_owner is None and roll_up(s, parent, parts_of(s, parent.id)):
        # Nothing runs any more (and no assembly holds the parent): cancelled at once.
        finish(s, parent, "cancelled", None, "cancelled; retry runs the cancelled parts again")


def retry_parts(s: Session, parent: Job) -> None:
    """Put the failed and cancelled parts back in the queue (the succeeded ones stay done);
    when none is left to run (the assembly failed), the assembly again."""
    again = [p for p in parts_of(s, parent.id, lock=True) if p.state in ("failed", "cancelled")]
    for part in again:
        part.state, part.stage, part.error, part.message = "queued", "queued", None, ""
        part.redeliveries, part.cancel_requested, part.finished_at = 0, False, None
        part.lease_owner = part.lease_expires_at = part.eta_s = part.dispatched_at = None
        state_event(s, part)
    parent.state, parent.error, parent.message = "queued", None, ""
    parent.redeliveries, parent.cancel_requested, parent.finished_at = 0, False, None
    parent.lease_owner = parent.lease_expires_at = parent.eta_s = None
    parent.stage = "queued" if again else "assembling"
    if not again:
        parent.state, parent.dispatched_at = "running", None


def to_dispatch(s: Session, job_id: str) -> list[str]:
    """After a retry: the ids to send to the broker (the queued parts, or the job itself when
    it runs as one or only its assembly is left)."""
    job = s.get(Job, job_id)
    if job is None:
        return []
    if not job.parts or job.stage == "assembling":
        return [job.id]
    return [p.id for p in parts_of(s, job_id) if p.state == "queued"]
