"""Whose job a free worker runs: the fair pick (issue 42, docs/design.md 4.2).

A message reaches the Celery parent when the worker has a free slot (acks late, prefetch 1:
`worker.celery_app`). Before a pool process starts, the parent asks `JobStore.pick` whether
the message's tenant has the turn, among the tenants with a waiting job and its own:

1. the tenant with the fewest jobs on a worker (a live lease, or picked and not yet claimed:
   its pool process is starting);
2. then the tenant served longest ago (its latest pick; one never served first);
3. then the one whose oldest waiting job is oldest.

If it has, the job is marked picked (`Job.picked_at`) and goes to the pool; if not, its message
goes back to the end of the queue (`worker.gate`: not an attempt, nothing written) and the
worker takes the next message. Within a tenant the queue's order holds. Picks are serialized
(SQLite runs one write transaction at a time; PostgreSQL takes an advisory lock), so two free
workers never both give one to a tenant because neither saw the other's pick.

Why rule 2: with one worker every tenant has nothing on a worker whenever it is free, so rules 1
and 3 alone are the queue's order (a tenant's three queued jobs before another's newer one);
the latest pick makes tenants take turns.

A waiting job is queued (or a parted job's assembly), sent to the broker, not picked within
the starting window, with no cancel asked and no parts of its own to wait for. The claim and its
lease (`JobStore.claim`) stay what keeps a job from running twice: the pick only orders.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any, Literal

from sqlalchemy import func, select, text
from sqlalchemy.orm import Session

from worker.models import Job, utcnow

__all__ = ["FairPick", "Pick", "Turn", "turns"]

NEVER = dt.datetime.min.replace(tzinfo=dt.timezone.utc)


@dataclass(frozen=True)
class Pick:
    """What `FairPick.pick` answers for one message."""

    status: Literal["run", "defer"]
    """run: its job goes to a pool process now; defer: its message goes back to the queue."""
    first: Turn | None = None
    """The tenant whose turn it is (its oldest waiting job), when not the message's."""


@dataclass(frozen=True, order=True)
class Turn:
    """A tenant's place in the pick: the smallest goes first (see the module)."""

    on_worker: int
    served: dt.datetime
    """Its latest pick (NEVER: not once)."""
    oldest: dt.datetime
    job: str
    """Its oldest waiting job (for the message's own tenant without one: the message's)."""
    tenant: str


def _waiting(since: dt.datetime) -> Any:
    """SQL: a job waiting for a worker (see the module); `since`: the starting window's start."""
    return ((Job.lease_owner.is_(None)) & (Job.cancel_requested.is_(False))
            & (Job.dispatched_at.is_not(None))
            & ((Job.picked_at.is_(None)) | (Job.picked_at < since))
            & (((Job.state == "queued") & (Job.parts == 0))
               | ((Job.state == "running") & (Job.stage == "assembling"))))


def _on_worker(now: dt.datetime, since: dt.datetime) -> Any:
    """SQL: a job that holds a worker: a live lease, or picked and not yet claimed."""
    return (((Job.state == "running") & (Job.lease_owner.is_not(None))
             & (Job.lease_expires_at > now))
            | ((Job.state == "queued") & (Job.lease_owner.is_(None)) & (Job.picked_at >= since)))


def turns(s: Session, job: Job, now: dt.datetime, since: dt.datetime) -> list[Turn]:
    """Every tenant with a waiting job, and `job`'s, in the order of their turns."""
    oldest: dict[str, tuple[dt.datetime, str]] = {}
    for tenant, job_id, created in s.execute(select(Job.tenant, Job.id, Job.created_at)
                                             .where(_waiting(since))
                                             .order_by(Job.created_at, Job.id)):
        oldest.setdefault(tenant, (created, job_id))
    oldest.setdefault(job.tenant, (job.created_at, job.id))
    busy = dict(s.execute(select(Job.tenant, func.count()).where(
        Job.tenant.in_(list(oldest)), _on_worker(now, since)).group_by(Job.tenant)).all())
    served = dict(s.execute(select(Job.tenant, func.max(Job.picked_at)).where(
        Job.tenant.in_(list(oldest)), Job.picked_at.is_not(None)).group_by(Job.tenant)).all())
    return sorted(Turn(busy.get(t, 0), served.get(t) or NEVER, created, job_id, t)
                  for t, (created, job_id) in oldest.items())


def _lock_picks(s: Session) -> None:
    """One pick at a time: SQLite's write transactions already run one at a time (BEGIN
    IMMEDIATE, worker.db); PostgreSQL takes a transaction-scoped advisory lock."""
    if s.get_bind().dialect.name == "postgresql":
        s.execute(text("SELECT pg_advisory_xact_lock(hashtext('dgs-fair-pick'))"))


class FairPick:
    """The job store's fair pick (see the module's docstring); `worker.store.JobStore`
    inherits it."""

    def pick(self, job_id: str, starting_seconds: float, *, force: bool = False) -> Pick:
        """Whether the message of `job_id`, at a free worker, runs now (its job is marked
        picked) or is deferred because another tenant has the turn. `starting_seconds`: how
        long a picked job counts as holding a worker before its claim. `force`: run it
        whatever the turn (the caller saw this message come round the whole queue)."""
        now = utcnow()
        since = now - dt.timedelta(seconds=starting_seconds)
        with self.session() as s:  # type: ignore[attr-defined]
            _lock_picks(s)
            job = s.get(Job, job_id)
            if job is None:  # deleted meanwhile: the claim says so
                return Pick("run")
            first = turns(s, job, now, since)[0]
            if first.tenant != job.tenant and not force:
                return Pick("defer", first)
            job.picked_at = now
            return Pick("run")
