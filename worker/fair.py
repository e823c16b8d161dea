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

A tenant that took every worker while alone would keep them until its jobs end: the fair share
(`FairPick.ask_to_yield`, asked by each running job's heartbeat thread, and between heartbeats
when `FairPick.watch` sees another tenant wait) asks one of its jobs to give its
worker up at the next step when another tenant waits with at least two jobs fewer on a worker
(the shares are then uneven by more than one worker; each tenant ends with its share, and no
two tenants trade a worker back and forth). The job stops with a checkpoint and goes back to the
queue (`JobStore.release`, no attempt counted), and its pool process runs the waiting tenant's
job itself (`FairPick.hand_over`, `worker.tasks`): the turn passes without the seconds of a
fresh process importing torch. One job is asked at a time, and only after holding its worker
`share_after_seconds` (every claim makes progress). A job picked before the waiting tenant came
gives its turn up as its process starts, before its claim and the seconds of its setup
(`FairPick.gives_way_at_start`). With fewer workers than tenants the shares cannot be even: time
slicing (`time_slice_seconds`, off by default) asks a job whenever another tenant waits with
fewer on a worker, after holding its worker that long; each slice costs a checkpoint.

A waiting job is queued (or a parted job's assembly), sent to the broker, not picked within
the starting window, with no cancel asked and no parts of its own to wait for. The claim and its
lease (`JobStore.claim`) stay what keeps a job from running twice: the pick only orders.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Collection
from dataclasses import dataclass
from typing import Any, Literal

from sqlalchemy import func, select, text
from sqlalchemy.orm import Session

from worker.models import Job, utcnow

__all__ = ["FairPick", "Pick", "Turn", "turns", "yield_wait"]

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


def _starting(since: dt.datetime) -> Any:
    """SQL: picked within the starting window and not claimed since (its pool process is
    starting); a job a worker gave back (`JobStore.release`) was claimed after its pick."""
    return ((Job.picked_at >= since)
            & ((Job.run_started_at.is_(None)) | (Job.run_started_at < Job.picked_at)))


def _waiting(since: dt.datetime) -> Any:
    """SQL: a job waiting for a worker (see the module); `since`: the starting window's start."""
    return ((Job.lease_owner.is_(None)) & (Job.cancel_requested.is_(False))
            & (Job.dispatched_at.is_not(None))
            & ((Job.picked_at.is_(None)) | ~_starting(since))
            & (((Job.state == "queued") & (Job.parts == 0))
               | ((Job.state == "running") & (Job.stage == "assembling"))))


def _others_waiting(tenant: str, since: dt.datetime) -> Any:
    """SQL: the tenants of the jobs of tenants other than `tenant` that wait for a worker."""
    return select(Job.tenant).where(_waiting(since), Job.tenant != tenant)


def _leased(now: dt.datetime) -> Any:
    """SQL: a running job under a live lease."""
    return ((Job.state == "running") & (Job.lease_owner.is_not(None))
            & (Job.lease_expires_at > now))


def _on_worker(now: dt.datetime, since: dt.datetime) -> Any:
    """SQL: a job that holds a worker: a live lease, or picked and not yet claimed."""
    return (_leased(now)
            | ((Job.state == "queued") & (Job.lease_owner.is_(None)) & _starting(since)))


def turns(s: Session, job: Job | None, now: dt.datetime, since: dt.datetime) -> list[Turn]:
    """Every tenant with a waiting job, and `job`'s, in the order of their turns."""
    oldest: dict[str, tuple[dt.datetime, str]] = {}
    for tenant, job_id, created in s.execute(select(Job.tenant, Job.id, Job.created_at)
                                             .where(_waiting(since))
                                             .order_by(Job.created_at, Job.id)):
        oldest.setdefault(tenant, (created, job_id))
    if job is not None:
        oldest.setdefault(job.tenant, (job.created_at, job.id))
    busy = dict(s.execute(select(Job.tenant, func.count()).where(
        Job.tenant.in_(list(oldest)), _on_worker(now, since)).group_by(Job.tenant)).all())
    served = dict(s.execute(select(Job.tenant, func.max(Job.picked_at)).where(
        Job.tenant.in_(list(oldest)), Job.picked_at.is_not(None)).group_by(Job.tenant)).all())
    return sorted(Turn(busy.get(t, 0), served.get(t) or NEVER, created, job_id, t)
                  for t, (created, job_id) in oldest.items())


def yield_wait(fewer: int, share_after: float, time_slice: float) -> float | None:
    """How long a job must have held its worker before it gives it up to a tenant waiting with
    `fewer` jobs on a worker than its own tenant (None: it keeps it; see the module)."""
    waits = [wait for wait, gap in ((share_after, 2), (time_slice, 1))
             if wait > 0 and fewer >= gap]
    return min(waits, default=None)


def _ahead(s: Session, tenant: str, others: Any, now: dt.datetime, since: dt.datetime) -> int:
    """How many jobs more `tenant` has on a worker than the waiting tenant with the fewest
    (`others`: the query of the other waiting tenants)."""
    tenants = set(s.scalars(others.distinct())) | {tenant}
    busy = dict(s.execute(select(Job.tenant, func.count()).where(
        Job.tenant.in_(list(tenants)), _on_worker(now, since)).group_by(Job.tenant)).all())
    return busy.get(tenant, 0) - min(busy.get(t, 0) for t in tenants - {tenant})


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

    def gives_way_at_start(self, job_id: str, *, share_after: float,
                           starting_seconds: float) -> bool:
        """Whether the picked job `job_id`, whose pool process is about to claim it, gives its
        turn up instead: since its pick another tenant has come to wait with at least two jobs
        fewer on a worker, so the fair share would ask it to stop as soon as it had held the
        worker `share_after` seconds, after the seconds of its setup. It goes back to waiting
        (not picked, not dispatched: a sweeper sends it again; no attempt counted) and the
        process runs the waiting tenant's job (`hand_over`). False with the fair share off."""
        if share_after <= 0:
            return False
        now = utcnow()
        since = now - dt.timedelta(seconds=starting_seconds)
        with self.session() as s:  # type: ignore[attr-defined]
            job = s.get(Job, job_id)
            if (job is None or job.state != "queued" or job.lease_owner is not None
                    or job.picked_at is None or job.cancel_requested or job.parts):
                return False
            others = _others_waiting(job.tenant, since)
            if s.scalar(others.limit(1)) is None:  # the usual answer, without the lock
                return False
            _lock_picks(s)
            if _ahead(s, job.tenant, others, now, since) < 2:
                return False
            job.picked_at = job.dispatched_at = None
            job.message = ("back in the queue: another tenant's job took its turn as its "
                           "worker started (fair share)")
            return True

    def hand_over(self, tenant: str, starting_seconds: float, *,
                  pipelines: Collection[str]) -> str | None:
        """The job that a pool process runs next itself, without a process start, after its
        job (of `tenant`) gave its worker up: the oldest waiting job of the tenant whose turn
        it is, marked picked. None when that tenant is `tenant` (the waiting tenant's job was
        picked elsewhere meanwhile), nobody waits, or the job's pipeline is not one of
        `pipelines` (those whose time limit fits in what the process has left)."""
        now = utcnow()
        since = now - dt.timedelta(seconds=starting_seconds)
        with self.session() as s:  # type: ignore[attr-defined]
            _lock_picks(s)
            first = next(iter(turns(s, None, now, since)), None)
            if first is None or first.tenant == tenant:
                return None
            job = s.get(Job, first.job)
            if job.pipeline not in pipelines:
                return None
            job.picked_at = now
            return job.id

    def watch(self, job_id: str, owner: str, *, starting_seconds: float) -> tuple[bool, bool]:
        """A running job's look between heartbeats, a read: (cancel requested, a job of another
        tenant waits for a worker). Nothing while `owner` does not hold the job (the heartbeat
        finds out that the lease was lost)."""
        since = utcnow() - dt.timedelta(seconds=starting_seconds)
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            job = s.execute(select(Job.tenant, Job.cancel_requested, Job.lease_owner)
                            .where(Job.id == job_id)).first()
            if job is None or job.lease_owner != owner:
                return False, False
            others = _others_waiting(job.tenant, since).limit(1)
            return bool(job.cancel_requested), s.scalar(others) is not None

    def ask_to_yield(self, job_id: str, owner: str, *, share_after: float, time_slice: float,
                     starting_seconds: float) -> bool:
        """Whether the running job `job_id` (leased by `owner`) should give its worker up now
        to a waiting tenant (see the module); when it should, the ask is recorded
        (`Job.yield_asked_at`) and no other job is asked until this one has left its worker."""
        now = utcnow()
        since = now - dt.timedelta(seconds=starting_seconds)
        with self.session() as s:  # type: ignore[attr-defined]
            job = s.get(Job, job_id)
            if (job is None or job.state != "running" or job.lease_owner != owner
                    or job.cancel_requested or job.yield_asked_at is not None
                    or job.run_started_at is None):
                return False
            others = _others_waiting(job.tenant, since)
            if s.scalar(others.limit(1)) is None:  # the usual answer, without the lock
                return False
            _lock_picks(s)
            live = _leased(now)
            if s.scalar(select(Job.id).where(live, Job.yield_asked_at.is_not(None))
                        .limit(1)) is not None:
                return False  # one ask at a time: the last has not left its worker yet
            wait = yield_wait(_ahead(s, job.tenant, others, now, since), share_after,
                              time_slice)
            if wait is None:
                return False
            held = now - dt.timedelta(seconds=wait)
            # Of the tenant's jobs that have held a worker that long, the one claimed last
            # gives way (the least run since its start); the others keep theirs.
            last = s.scalar(select(Job.id).where(live, Job.tenant == job.tenant,
                                                 Job.run_started_at <= held,
                                                 Job.cancel_requested.is_(False))
                            .order_by(Job.run_started_at.desc(), Job.id.desc()).limit(1))
            if last != job.id:
                return False
            job.yield_asked_at = now
            return True
