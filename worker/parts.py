"""A sequence job run as parts (docs/design.md 4.4): one part per group of pictures, each a row
of `jobs` with `parent_id` set, so that a part has everything a job has (its lease, heartbeat,
attempts, broker message, checkpoints, cancel) without a second copy of that machinery. This
module holds what is particular to parts: how the parts' states roll up into the parent's, and
the parent's overall progress read from its parts (how a job is split is
`core.config.independent_groups`, the groups its run plans); `worker.transitions` applies these to
the rows for the job store. Torch-free (the API reads parts when it shows a job)."""

from __future__ import annotations

import datetime as dt
from typing import Any

from sqlalchemy import delete, exists, select
from sqlalchemy.orm import Session, aliased

from worker.models import Job, JobEvent, utcnow

__all__ = ["ASSEMBLY_SHARE", "active_parts", "delete_parts", "failed_error", "overall_progress",
           "part_event", "part_out", "parts_of", "roll_up", "worker_of"]

ASSEMBLY_SHARE = 0.01
"""Share of a parted job's progress left for the assembly (merge, evaluation, publishing)."""


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
