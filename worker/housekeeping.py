"""What the sweepers ask of the job store (`worker.sweeper`): which jobs no worker has and no
broker message will bring to one, and sending them again; `worker.store.JobStore` inherits
it."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from typing import Any

from sqlalchemy import select

from worker.models import Job, utcnow
from worker.parts import active_parts

__all__ = ["Housekeeping"]


class Housekeeping:
    """The job store's housekeeping (see the module's docstring)."""

    def stranded(self, *, held: set[str] | None = None, grace: float = 0.0,
                 requeue_after: float | None = None) -> dict[str, str]:
        """Jobs that no worker has and no message will bring to one, with why: running with
        an expired lease; queued and never sent (released by a worker that shut down, or the
        broker was away when it was made); with `held` (the jobs the broker holds a message
        for, worker.broker), queued, sent more than `grace` seconds ago and not held; with
        `requeue_after` (for a broker that cannot be inspected), queued and last sent longer
        ago than that."""
        now = utcnow()
        out: dict[str, str] = {}
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            # A parted job's own turn (its assembly) comes when no part is left to run.
            for job_id, owner in s.execute(select(Job.id, Job.lease_owner).where(
                    Job.state == "running", ~active_parts(Job.id),
                    (Job.lease_owner.is_(None)) | (Job.lease_expires_at < now))):
                out[job_id] = f"its worker ({owner}) stopped renewing its lease"
            for job_id, sent in s.execute(select(Job.id, Job.dispatched_at).where(
                    Job.state == "queued", Job.lease_owner.is_(None), ~active_parts(Job.id))):
                if sent is None:
                    out[job_id] = ("it was never sent to the broker (released by a worker that "
                                   "shut down or gave it up to another tenant, or the broker "
                                   "was away)")
                elif held is not None and job_id not in held and \
                        sent < now - dt.timedelta(seconds=grace):
                    out[job_id] = "it is queued, but its message is no longer in the broker"
                elif requeue_after is not None and \
                        sent < now - dt.timedelta(seconds=requeue_after):
                    out[job_id] = (f"it has been queued for more than {requeue_after:.0f} s "
                                   "(this broker cannot be inspected)")
        return out

    def leases_of(self, prefix: str) -> list[tuple[str, float]]:
        """(job id, seconds its lease has left, negative once lapsed) of every running job
        whose lease owner begins with `prefix` (one worker process: worker.lease.lease_prefix),
        for its worker's watchdog (worker.watchdog)."""
        now = utcnow()
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            rows = s.execute(select(Job.id, Job.lease_expires_at).where(
                Job.state == "running", Job.lease_owner.startswith(prefix, autoescape=True)))
            return [(job_id, (expires - now).total_seconds() if expires else 0.0)
                    for job_id, expires in rows]

    def redispatch_stranded(self, send: Callable[[str], None], *, min_gap: float,
                            **stranded: Any) -> dict[str, str]:
        """Send every stranded job (`stranded(**stranded)`) to the broker again, at most once
        per `min_gap` seconds per job whoever else sweeps; returns {job id: why} of those
        sent."""
        sent = {}
        before = utcnow() - dt.timedelta(seconds=min_gap)
        for job_id, why in self.stranded(**stranded).items():
            if self.mark_dispatched(job_id, before=before):  # type: ignore[attr-defined]
                send(job_id)
                sent[job_id] = why
        return sent
