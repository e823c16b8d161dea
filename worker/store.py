"""The job store: every state change of a job, made by the API or by a worker, goes through here.

A job is run by whoever holds its lease. A worker claims the lease atomically (a conditional
UPDATE), renews it with every heartbeat, and loses it when it stops renewing; only the holder may
write progress or finish the job. So a message delivered twice, a worker that was presumed dead,
or two sweepers racing can never run one job twice at the same time (docs/design.md section 4).

States: queued -> running -> succeeded | failed | cancelled; `retry` puts a failed or cancelled
job back to queued (it resumes from its checkpoint). Every change appends a JobEvent, the stream
that the API serves as server-sent events.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Literal

from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from worker import transitions
from worker.api_queries import ApiQueries
from worker.db import session_scope
from worker.fair import FairPick, Pick
from worker.housekeeping import Housekeeping
from worker.idempotency import Idempotency, remember
from worker.lease import Owner, run_ended, run_started
from worker.models import Artifact, Job, JobEvent, JobLog, utcnow
from worker.parts import active_parts, part_event, parts_of
from worker.quota import CapReached, lock_tenant
from worker.transitions import ACTIVE, TERMINAL, JobState, new_id, progress_of

__all__ = [
    "ACTIVE",
    "TERMINAL",
    "CapReached",
    "Claim",
    "JobStore",
    "NotCreated",
    "Owner",
    "Pick",
    "new_id",
    "progress_of",
]


class NotCreated(Exception):
    """A job was not made, and nothing of it kept: a live submit holds its Idempotency-Key
    (`worker.idempotency`), or the capture it names was deleted meanwhile."""


@dataclass(frozen=True)
class Claim:
    """The outcome of `JobStore.claim`."""

    status: Literal["claimed", "leased", "terminal", "missing", "exhausted", "waiting"]
    """claimed: run it; leased: another live worker holds it (for `retry_in` more seconds,
    and longer while it renews); terminal: it finished or was cancelled meanwhile; missing:
    deleted; exhausted: the redelivery cap was reached (the job is now failed); waiting: a
    parted job whose parts are still queued or running (it is assembled after them)."""
    job: Job | None = None
    retry_in: float = 0.0


def _nothing_to_run(s: Session, job: Job | None, now: dt.datetime) -> Claim | None:
    """A message for `job` that finds nothing to run: it was deleted, has ended, is a parted
    job waiting for its parts, or a live worker holds its lease; None otherwise (a cancel
    requested is left to the claim, which records it)."""
    if job is None:
        return Claim("missing")
    if job.state in TERMINAL:
        return Claim("terminal", job)
    if job.cancel_requested:
        return None
    if job.parts and s.scalar(select(active_parts(job.id))):
        return Claim("waiting", job)
    if job.lease_owner is not None and job.lease_expires_at and job.lease_expires_at > now:
        holder = Owner.parse(job.lease_owner)
        if holder is None or not holder.is_dead_here():
            return Claim("leased", job, (job.lease_expires_at - now).total_seconds())
    return None


class JobStore(ApiQueries, Housekeeping, FairPick):
    """Job lifecycle operations on the database at `url`, each in its own transaction (the
    changes to the rows, those of jobs run as parts included, in `worker.transitions`; the API's
    pages and deletions in `worker.api_queries.ApiQueries`; the sweepers' questions in
    `worker.housekeeping.Housekeeping`; whose turn a free worker gives, `worker.fair`)."""

    def __init__(self, url: str):
        self.url = url

    def session(self, write: bool = True):
        return session_scope(self.url, write)

    @contextmanager
    def _creating(self) -> Iterator[Session]:
        """A write session whose constraint failures (on flush or commit) raise NotCreated,
        so callers need not know the database's exceptions."""
        try:
            with self.session() as s:
                yield s
        except IntegrityError as exc:
            raise NotCreated(str(exc.orig).splitlines()[0]) from exc

    @staticmethod
    def active_jobs(s: Session, tenant: str, cap: int | None = None) -> int:
        """How many jobs of `tenant` are queued or running (a job run as parts counts once),
        in session `s`. With `cap`: the count is taken under the tenant's lock
        (`worker.quota.lock_tenant`, held until `s` ends) and CapReached is raised when it is
        `cap` or more, so a job added in `s` cannot pass the cap with a concurrent one."""
        if cap is not None:
            lock_tenant(s, tenant)
        active = s.scalar(select(func.count()).select_from(Job).where(
            Job.tenant == tenant, Job.parent_id.is_(None), Job.state.in_(ACTIVE)))
        if cap is not None and active >= cap:
            raise CapReached(active, cap)
        return active

    # -- created and changed by the API -------------------------------------------------------
    def create(self, tenant: str, pipeline: str, params: dict[str, Any], *,
               capture_id: str | None, name: str = "", expires_at: dt.datetime | None = None,
               idempotency: Idempotency | None = None, cap: int | None = None,
               resolved_run: dict[str, Any] | None = None) -> Job:
        """A queued job (`resolved_run`: a reconstruction's run, resolved at submit); with
        `idempotency`, its key is kept with it in the same transaction (NotCreated, and no
        job, when a live row has the key: `worker.idempotency`). `cap`: CapReached, and no
        job, when the tenant has that many active (`active_jobs`)."""
        with self._creating() as s:
            self.active_jobs(s, tenant, cap)
            job = Job(id=new_id("job"), tenant=tenant, capture_id=capture_id, pipeline=pipeline,
                      params=params, name=name, state="queued", stage="queued",
                      expires_at=expires_at, resolved_run=resolved_run)
            s.add(job)
            s.flush()
            remember(s, idempotency, job.id)
            transitions.state_event(s, job)
            return job

    def create_parted(self, tenant: str, pipeline: str, params: dict[str, Any],
                      groups: list[list[str]], *,
                      capture_id: str | None, name: str = "",
                      expires_at: dt.datetime | None = None,
                      idempotency: Idempotency | None = None,
                      cap: int | None = None,
                      resolved_run: dict[str, Any] | None = None) -> tuple[Job, list[Job]]:
        """A sequence job and its parts (one per group of `groups`), all queued; the caller
        dispatches the parts (the parent itself is dispatched when they have succeeded).
        `idempotency`, `cap`, `resolved_run`: as `create` (the key names the parent; the job
        counts once; every part runs the same run)."""
        with self._creating() as s:
            self.active_jobs(s, tenant, cap)
            return transitions.create_parted(s, tenant, pipeline, params, groups,
                                             capture_id=capture_id, name=name,
                                             expires_at=expires_at, idempotency=idempotency,
                                             resolved_run=resolved_run)

    def create_render(self, tenant: str, source_job_id: str, pipeline: str,
                      params: dict[str, Any], *, name: str = "",
                      expires_at: dt.datetime | None = None,
                      idempotency: Idempotency | None = None,
                      cap: int | None = None) -> Job | None:
        """A job on the results of `source_job_id`, a succeeded job of `tenant` (on its
        capture); None when the source is not that (any more). The source row is locked
        while the job is added, so a concurrent delete of the source either happens first
        (None here) or waits and then sees this job (and refuses). `idempotency`, `cap`: as
        `create`."""
        with self._creating() as s:
            self.active_jobs(s, tenant, cap)
            source = s.get(Job, source_job_id, with_for_update=True)
            if source is None or source.tenant != tenant or source.state != "succeeded":
                return None
            job = Job(id=new_id("job"), tenant=tenant, capture_id=source.capture_id,
                      source_job_id=source.id, pipeline=pipeline, params=params, name=name,
                      state="queued", stage="queued", expires_at=expires_at)
            s.add(job)
            s.flush()
            remember(s, idempotency, job.id)
            transitions.state_event(s, job)
            return job

    def get(self, job_id: str, tenant: str | None = None) -> Job | None:
        """The job, or None when it does not exist or belongs to another tenant."""
        with self.session(write=False) as s:
            job = s.get(Job, job_id)
            if job is None or (tenant is not None and job.tenant != tenant):
                return None
            return job

    def mark_dispatched(self, job_id: str, *, before: dt.datetime | None = None) -> bool:
        """Record a dispatch to the broker; with `before`, only if the last dispatch was earlier
        (so concurrent sweepers send one message, not two). True when this caller may send."""
        with self.session() as s:
            q = update(Job).where(Job.id == job_id, Job.state.in_(ACTIVE))
            if before is not None:
                q = q.where((Job.dispatched_at.is_(None)) | (Job.dispatched_at < before))
            res = s.execute(q.values(dispatched_at=utcnow(), dispatches=Job.dispatches + 1)
                            .execution_options(synchronize_session=False))
            return res.rowcount == 1

    def request_cancel(self, job_id: str, tenant: str) -> Job | None:
        """Cancel: a queued job is cancelled at once; a running one is flagged and its worker
        stops between two steps (and ends its process if that takes too long)."""
        with self.session() as s:
            job = s.get(Job, job_id, with_for_update=True)
            if job is None or job.tenant != tenant:
                return None
            if job.parts and job.state in ACTIVE:
                job.cancel_requested = True
                transitions.event(s, job.id, "state", {"state": job.state,
                                                       "cancel_requested": True})
                transitions.cancel_parts(s, job)
            elif job.state == "queued" and job.lease_owner is None:
                job.state, job.stage, job.finished_at = "cancelled", "cancelled", utcnow()
                job.eta_s = None
                transitions.state_event(s, job)
            elif job.state in ACTIVE and not job.cancel_requested:
                job.cancel_requested = True
                transitions.event(s, job.id, "state", {"state": job.state,
                                                       "cancel_requested": True})
            return job

    def retry(self, job_id: str, tenant: str, cap: int | None = None) -> Job | None:
        """Put a failed or cancelled job back in the queue; the caller dispatches it. Returns the
        job (unchanged when it was not failed or cancelled). `cap`: as `create`."""
        with self.session() as s:
            if cap is not None:  # the tenant's lock before the row's, as `create` takes them
                lock_tenant(s, tenant)
            job = s.get(Job, job_id, with_for_update=True)
            if job is None or job.tenant != tenant:
                return None
            if cap is not None and job.state in ("failed", "cancelled"):
                self.active_jobs(s, tenant, cap)
            if job.parts and job.state in ("failed", "cancelled"):
                transitions.retry_parts(s, job)
                transitions.state_event(s, job)
            elif job.state in ("failed", "cancelled"):
                job.state, job.stage, job.error, job.message = "queued", "queued", None, ""
                job.redeliveries, job.cancel_requested, job.finished_at = 0, False, None
                job.lease_owner = job.lease_expires_at = job.eta_s = None
                transitions.state_event(s, job)
            return job

    def to_dispatch(self, job_id: str) -> list[str]:
        """After a retry: the ids to send to the broker (the queued parts of a job run as
        parts, or the job itself)."""
        with self.session(write=False) as s:
            return transitions.to_dispatch(s, job_id)

    def parts(self, parent_id: str) -> list[Job]:
        """The parent's parts in order (empty for a job that runs as one)."""
        with self.session(write=False) as s:
            return parts_of(s, parent_id)

    # -- used by workers ---------------------------------------------------------------------
    def claim(self, job_id: str, owner: Owner, lease_seconds: float, max_attempts: int) -> Claim:
        """Take the job's lease (and count an attempt) unless a live worker holds it."""
        now = utcnow()
        with self.session() as s:
            job = transitions.lock(s, job_id)
            refused = _nothing_to_run(s, job, now)
            if refused is not None:
                return refused
            if job.cancel_requested:
                transitions.finish(s, job, "cancelled", None, "cancelled before it resumed")
                return Claim("terminal", job)
            if job.redeliveries >= max_attempts:
                transitions.finish(s, job, "failed", {
                    "code": "worker_lost", "retryable": True,
                    "message": f"the worker running this job was lost {job.redeliveries} "
                               f"times (redelivery cap {max_attempts}); retry resumes from the "
                               "last checkpoint"}, "")
                return Claim("exhausted", job)
            job.attempts += 1
            job.redeliveries += 1
            run_started(job, owner, now)
            job.lease_owner, job.lease_expires_at = str(owner), now + dt.timedelta(
                seconds=lease_seconds)
            job.state = "running"
            job.started_at = job.started_at or now
            job.run_started_at, job.run_start_fraction = now, job.fraction
            job.yield_asked_at = None
            job.stage, job.eta_s = "starting", None
            transitions.state_event(s, job)
            if job.parent_id is not None:
                transitions.part_claimed(s, job)
            return Claim("claimed", job)

    def peek(self, job_id: str) -> Claim | None:
        """What `claim` would answer for a job with nothing to run (missing, terminal, waiting
        or leased), reading only; None when a claim may run it (or must record its cancel)."""
        with self.session(write=False) as s:
            return _nothing_to_run(s, s.get(Job, job_id), utcnow())

    def heartbeat(self, job_id: str, owner: Owner, lease_seconds: float,
                  progress: dict[str, Any] | None = None, *,
                  milestones: Sequence[dict[str, Any]] = ()) -> tuple[bool, bool]:
        """Renew the lease and write each of `milestones`, then `progress` (fraction never
        decreases; each appends an event, in that order). Returns (still the owner, cancel
        requested)."""
        with self.session() as s:
            job = s.get(Job, job_id, with_for_update=True)
            if job is None or job.lease_owner != str(owner) or job.state != "running":
                return False, bool(job is None or job.cancel_requested)
            job.lease_expires_at = utcnow() + dt.timedelta(seconds=lease_seconds)
            for state in [*milestones, progress]:
                if not state:
                    continue
                fraction = float(state.get("fraction", job.fraction))
                for key in ("stage", "frame", "frames", "iteration", "iterations", "message"):
                    if key in state:
                        setattr(job, key, state[key])
                job.fraction = min(1.0, max(job.fraction, fraction))
                job.eta_s = state.get("eta_s", job.eta_s)
                transitions.event(s, job.id, "progress", progress_of(job))
                if job.parent_id is not None:
                    part_event(s, job, "progress", progress_of(job))
            return True, job.cancel_requested

    def finish(self, job_id: str, owner: Owner, state: JobState,
               error: dict[str, Any] | None = None, message: str = "") -> bool:
        """End the job (only its lease holder may); False when the lease was lost."""
        with self.session() as s:
            job = transitions.lock(s, job_id)
            if job is None or job.lease_owner != str(owner):
                return False
            transitions.finish(s, job, state, error, message)
            return True

    def release(self, job_id: str, owner: Owner, message: str) -> bool:
        """Give the job back to the queue without ending it (its worker is shutting down, or
        it gave its worker to another tenant: `worker.fair`).
        It is marked as never dispatched, so the next sweeper pass of any other process (the
        API's, another worker's) sends it, and another worker resumes it from its checkpoint;
        the worker going down must not send it itself, or it may take the job back while its
        consumer is still open. The attempt does not count towards the redelivery cap. False
        when the lease was lost."""
        with self.session() as s:
            job = s.get(Job, job_id, with_for_update=True)
            if job is None or job.lease_owner != str(owner) or job.state != "running":
                return False
            job.state, job.stage, job.message = "queued", "queued", message[:512]
            run_ended(job, "released", utcnow())
            job.lease_owner = job.lease_expires_at = job.eta_s = job.dispatched_at = None
            job.redeliveries = max(job.redeliveries - 1, 0)
            transitions.state_event(s, job)
            return True

    def append_logs(self, job_id: str, lines: Sequence[str]) -> None:
        """Append lines to the job's log (seq continues where it ends)."""
        if not lines:
            return
        for _ in range(5):  # two writers racing for the same seq: the loser retries
            try:
                with self.session() as s:
                    last = s.scalar(select(func.max(JobLog.seq)).where(JobLog.job_id == job_id))
                    start = -1 if last is None else last
                    s.add_all(JobLog(job_id=job_id, seq=start + 1 + i, line=line[:4000])
                              for i, line in enumerate(lines))
                return
            except IntegrityError:
                continue
        raise RuntimeError(f"job {job_id}: could not append to the log")

    def add_artifact(self, job_id: str, path: str, *, kind: str, size: int, sha256: str,
                     content_type: str, frame: str | None = None) -> None:
        """Record (or replace) one artifact of the job."""
        with self.session() as s:
            row = s.scalar(select(Artifact).where(Artifact.job_id == job_id,
                                                  Artifact.path == path))
            if row is None:
                s.add(Artifact(job_id=job_id, path=path, kind=kind, size=size, sha256=sha256,
                               content_type=content_type, frame=frame))
            else:
                row.kind, row.size, row.sha256 = kind, size, sha256
                row.content_type, row.frame, row.created_at = content_type, frame, utcnow()

    # -- read by the API ---------------------------------------------------------------------
    def events_after(self, job_id: str, after: int, limit: int = 500) -> list[JobEvent]:
        with self.session(write=False) as s:
            return list(s.scalars(select(JobEvent).where(JobEvent.job_id == job_id,
                                                         JobEvent.id > after)
                                  .order_by(JobEvent.id).limit(limit)))

    def logs(self, job_id: str, offset: int, limit: int) -> list[JobLog]:
        with self.session(write=False) as s:
            return list(s.scalars(select(JobLog).where(JobLog.job_id == job_id,
                                                       JobLog.seq >= offset)
                                  .order_by(JobLog.seq).limit(limit)))
