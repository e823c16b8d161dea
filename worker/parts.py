"""A sequence job run as parts (docs/design.md 4.4): one part per group of pictures, each a row
of `jobs` with `parent_id` set, so that a part has everything a job has (its lease, heartbeat,
attempts, broker message, checkpoints, cancel) without a second copy of that machinery. This
module holds what is particular to parts: how a job is split, how the parts' states roll up
into the parent's, and the parent's overall progress read from its parts. Torch-free (the API
splits a job when it is posted)."""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from typing import Any

from sqlalchemy import delete, exists, select
from sqlalchemy.orm import Session, aliased

from core.config import RunConfig
from worker.idempotency import Idempotency, remember
from worker.models import Job, JobEvent, utcnow

__all__ = ["ASSEMBLY_SHARE", "PartOps", "active_parts", "delete_parts", "overall_progress",
           "part_out", "parts_of", "roll_up", "split_frames", "worker_of"]

ASSEMBLY_SHARE = 0.01
"""Share of a parted job's progress left for the assembly (merge, evaluation, publishing)."""


def split_frames(frames: Sequence[str], cfg: RunConfig) -> list[list[str]] | None:
    """The frames of each part of a reconstruction of `frames` with `cfg`: one part per group of
    pictures (`core.sequence.segment`: consecutive runs of `gop` frames), one per frame when
    `sequence.enabled` is off. None when the job runs as one: a single group, or groups that
    are not independent (`sequence.refine_scope` "run": a group spends what earlier groups
    saved, so it has to wait for them)."""
    if cfg.sequence.enabled and cfg.sequence.refine_scope != "group":
        return None
    gop = cfg.gop if cfg.sequence.enabled else 1
    groups = [list(frames[s:s + gop]) for s in range(0, len(frames), gop)]
    return groups if len(groups) > 1 else None


def active_parts(job_id) -> Any:
    """SQL: the job has a queued or running part."""
    part = aliased(Job)
    return exists().where(part.parent_id == job_id, part.state.in_(("queued", "running")))


def parts_of(s: Session, parent_id: str, *, lock: bool = False) -> list[Job]:
    """The parent's parts in order."""
    q = select(Job).where(Job.parent_id == parent_id).order_by(Job.part_index)
    return list(s.scalars(q.with_for_update() if lock else q))


def delete_parts(s: Session, parent_id: str) -> list[str]:
    """Delete a parent's part rows (their events and logs cascade); returns their ids, whose
    files (jobs/<id>/) the caller deletes."""
    ids = list(s.scalars(select(Job.id).where(Job.parent_id == parent_id)))
    if ids:
        s.execute(delete(Job).where(Job.parent_id == parent_id)
                  .execution_options(synchronize_session=False))
    return ids


def roll_up(s: Session, parent: Job, parts: list[Job]) -> str | None:
    """What the parent becomes now that a part changed: None while a part is queued or
    running; "assemble" when every part succeeded (the parent waits, unleased and undispatched,
    for a worker to assemble it); "failed" or "cancelled" otherwise (a cancel asked for wins
    over a part's failure). The caller finishes the parent accordingly."""
    states = [p.state for p in parts]
    if any(state in ("queued", "running") for state in states):
        return None
    if parent.cancel_requested:
        return "cancelled"
    if all(state == "succeeded" for state in states):
        return "assemble"
    return "failed" if "failed" in states else "cancelled"


def failed_error(parts: list[Job]) -> dict[str, Any]:
    """The parent's error when parts failed: the first failed part's, naming it."""
    failed = [p for p in parts if p.state == "failed"]
    first = failed[0]
    error = dict(first.error or {"code": "internal", "retryable": True, "message": ""})
    frames = first.part_frames or []
    where = f"{frames[0]}..{frames[-1]}" if frames else "?"
    error["message"] = (f"{len(failed)} of {len(parts)} parts failed; part {first.part_index} "
                        f"(frames {where}): {error.get('message', '')}; retry runs the failed "
                        "parts again")[:2000]
    error["retryable"] = True
    return error


def worker_of(job: Job) -> str | None:
    """host/pid of the worker that runs `job` or ran it last (from its lease for a row claimed
    before migration 0004 kept it)."""
    if job.worker is None and job.lease_owner:
        return "/".join(job.lease_owner.split("/")[:2])
    return job.worker


def part_out(part: Job) -> dict[str, Any]:
    """A part as the API shows it."""
    return {"index": part.part_index, "frames": list(part.part_frames or []),
            "state": part.state, "worker": worker_of(part), "runs": list(part.runs or []),
            "attempts": part.attempts,
            "stage": part.stage, "frame": part.frame, "iteration": part.iteration,
            "iterations": part.iterations, "fraction": round(part.fraction, 6),
            "eta_s": part.eta_s, "started_at": part.started_at,
            "finished_at": part.finished_at, "error": part.error}


def _rate(part: Job, now: dt.datetime) -> float | None:
    """Frames per second this part's current run has made (None before a measurable run)."""
    if part.state != "running" or part.run_started_at is None:
        return None
    elapsed = (now - part.run_started_at).total_seconds()
    done = (part.fraction - part.run_start_fraction) * len(part.part_frames or [1])
    return done / elapsed if elapsed > 2.0 and done > 1e-3 else None


def overall_progress(parent: Job, parts: list[Job]) -> dict[str, Any]:
    """The parent's progress from its parts': the fraction of frames done (weighted by each
    part's frames, `ASSEMBLY_SHARE` kept for the assembly) and an ETA from the measured rates
    of the running parts (the remaining frames over their summed rate, and never less than the
    slowest running part's own ETA: the longest group bounds the job)."""
    if parent.state != "running" or not any(p.state in ("queued", "running") for p in parts):
        return {}  # queued, ended or assembling: the parent's own progress says it
    sizes = [max(len(p.part_frames or []), 1) for p in parts]
    total = float(sum(sizes))
    fraction = sum(p.fraction * n for p, n in zip(parts, sizes, strict=True)) / total
    now = utcnow()
    rates = [r for r in (_rate(p, now) for p in parts) if r is not None]
    eta = None
    if rates:
        left = sum((1 - p.fraction) * n for p, n in zip(parts, sizes, strict=True)
                   if p.state != "succeeded")
        longest = max((p.eta_s or 0.0) for p in parts if p.state == "running")
        eta = round(max(left / sum(rates), longest), 1)
    running = [p for p in parts if p.state == "running"]
    done = sum(p.state == "succeeded" for p in parts)
    return {"fraction": min(fraction * (1 - ASSEMBLY_SHARE), 1 - ASSEMBLY_SHARE),
            "eta_s": eta if parent.state == "running" else None,
            "frames": int(total), "frame": sum(n for p, n in zip(parts, sizes, strict=True)
                                               if p.state == "succeeded"),
            "stage": parent.stage if not running else "parts",
            "message": f"{done} of {len(parts)} parts done, {len(running)} running"}


def part_event(s: Session, part: Job, kind: str, data: dict[str, Any]) -> None:
    """An event of the parent that says what one of its parts did (SSE kind `part`)."""
    s.add(JobEvent(job_id=part.parent_id, kind="part",
                   data={"part": part.part_index, "event": kind, **data}))


class PartOps:
    """The job store's operations on parted jobs (`worker.store.JobStore` inherits them)."""

    def create_parted(self, tenant: str, params: dict[str, Any], groups: list[list[str]], *,
                      capture_id: str | None, name: str = "",
                      expires_at: dt.datetime | None = None,
                      idempotency: Idempotency | None = None) -> tuple[Job, list[Job]]:
        """A sequence job and its parts (one per group of `groups`), all queued; the caller
        dispatches the parts (the parent itself is dispatched when they have succeeded).
        `idempotency`: as `JobStore.create` (the key names the parent)."""
        new_id = self._new_id  # type: ignore[attr-defined]
        with self.session() as s:  # type: ignore[attr-defined]
            parent = Job(id=new_id("job"), tenant=tenant, capture_id=capture_id,
                         pipeline="reconstruct", params=params, name=name, state="queued",
                         stage="queued", expires_at=expires_at, parts=len(groups),
                         frames=sum(map(len, groups)))
            s.add(parent)
            s.flush()
            remember(s, idempotency, parent.id)
            parts = [Job(id=new_id("job"), tenant=tenant, capture_id=capture_id,
                         pipeline="reconstruct", params=params, name=name, state="queued",
                         stage="queued", parent_id=parent.id, part_index=i, part_frames=frames,
                         frames=len(frames))
                     for i, frames in enumerate(groups)]
            s.add_all(parts)
            s.flush()
            self._state_event(s, parent)  # type: ignore[attr-defined]
            return parent, parts

    @staticmethod
    def _lock(s: Session, job_id: str) -> Job | None:
        """The job's row locked; a part's parent is locked first, so that every transaction
        that locks both (a part's claim or end, a cancel of its job) takes them in the same
        order and none waits for another in a cycle (PostgreSQL)."""
        parent_id = s.scalar(select(Job.parent_id).where(Job.id == job_id))
        if parent_id is not None:
            s.get(Job, parent_id, with_for_update=True)
        return s.get(Job, job_id, with_for_update=True)

    def _roll_up(self, s: Session, part: Job) -> None:
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
            self._state_event(s, parent)  # type: ignore[attr-defined]
        elif outcome == "failed":
            self._finish(s, parent, "failed", failed_error(parts), "")  # type: ignore
        elif outcome == "cancelled":
            self._finish(s, parent, "cancelled", None,  # type: ignore[attr-defined]
                         "cancelled; retry runs the cancelled parts again")

    def _part_claimed(self, s: Session, part: Job) -> None:
        """A part started: its parent is running from then on."""
        parent = s.get(Job, part.parent_id, with_for_update=True)
        if parent is not None and parent.state == "queued":
            parent.state, parent.stage = "running", "parts"
            parent.started_at = parent.started_at or utcnow()
            self._state_event(s, parent)  # type: ignore[attr-defined]

    def _cancel_parts(self, s: Session, parent: Job) -> None:
        """Cancel every part: a queued one at once, a running one at its next step."""
        for part in parts_of(s, parent.id, lock=True):
            if part.state == "queued" and part.lease_owner is None:
                part.state, part.stage, part.finished_at = "cancelled", "cancelled", utcnow()
                part.eta_s = None
                self._state_event(s, part)  # type: ignore[attr-defined]
            elif part.state in ("queued", "running"):
                part.cancel_requested = True
                part_event(s, part, "state", {"state": part.state, "cancel_requested": True})
        s.flush()
        if parent.lease_owner is None and roll_up(s, parent, parts_of(s, parent.id)):
            # Nothing runs any more (and no assembly holds the parent): cancelled at once.
            self._finish(s, parent, "cancelled", None,  # type: ignore[attr-defined]
                         "cancelled; retry runs the cancelled parts again")

    def _retry_parts(self, s: Session, parent: Job) -> None:
        """Put the failed and cancelled parts back in the queue (the succeeded ones stay
        done); when none is left to run (the assembly failed), the assembly again."""
        again = [p for p in parts_of(s, parent.id, lock=True)
                 if p.state in ("failed", "cancelled")]
        for part in again:
            part.state, part.stage, part.error, part.message = "queued", "queued", None, ""
            part.attempts, part.cancel_requested, part.finished_at = 0, False, None
            part.lease_owner = part.lease_expires_at = part.eta_s = part.dispatched_at = None
            self._state_event(s, part)  # type: ignore[attr-defined]
        parent.state, parent.error, parent.message = "queued", None, ""
        parent.attempts, parent.cancel_requested, parent.finished_at = 0, False, None
        parent.lease_owner = parent.lease_expires_at = parent.eta_s = None
        parent.stage = "queued" if again else "assembling"
        if not again:
            parent.state, parent.dispatched_at = "running", None

    def to_dispatch(self, job_id: str) -> list[str]:
        """After a retry: the ids to send to the broker (the queued parts, or the parent when
        only its assembly is left)."""
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            job = s.get(Job, job_id)
            if job is None:
                return []
            if not job.parts or job.stage == "assembling":
                return [job.id]
            return [p.id for p in parts_of(s, job_id) if p.state == "queued"]

    def parts(self, parent_id: str) -> list[Job]:
        """The parent's parts in order (empty for a job that runs as one)."""
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            return parts_of(s, parent_id)
