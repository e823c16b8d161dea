"""Housekeeping that keeps the queue honest: re-send jobs that no message will bring to a worker,
delete what has expired (explicit `expires_at` only; every deletion is logged), and remove the
scratch folders of jobs this machine's workers no longer run.

A worker killed outright (SIGKILL of the whole worker, a machine gone) may take its broker
message with it: the SQLite transport hides a delivered message until it is acknowledged, Redis
until its visibility timeout (days). The job store knows better: a running job whose lease has
expired has no worker, and is sent again at once (every `interval`, a quarter lease). A queued
job is sent again only when its message is really gone: every `lost_message_seconds` the
sweeper asks the broker which jobs it still holds a message for (worker.broker); one that merely
waits behind others is never sent twice. The lease makes any duplicate harmless (the worker
that receives it drops it, worker.runner). Any number of sweepers may run (API processes,
workers): `JobStore.mark_dispatched` lets one of them send.

A worker's sweeper thread lives in the Celery parent, whose pool processes start as fresh
interpreters (worker.celery_app): none inherits a lock the sweeper held in SQLite.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable

from sqlalchemy import select, update

from worker.api_queries import assets_named
from worker.blobs import BlobStore, open_store
from worker.idempotency import forget_expired
from worker.models import Asset, Capture, Job, utcnow
from worker.parts import delete_parts
from worker.periodic import Periodic
from worker.scratch import clean_capture_folders, clean_job_folders
from worker.settings import WorkerSettings
from worker.store import ACTIVE, TERMINAL, JobStore

__all__ = ["Sweeper"]

log = logging.getLogger("dgs.sweeper")
HeldJobs = Callable[[float], "set[str] | None"]

class Sweeper:
    """`sweep()` once, or `start()` a daemon thread that sweeps every `interval` seconds.

    `held(grace)` answers the jobs the broker holds a message for (worker.broker's
    `BrokerInspector.held_jobs`), or None for a broker that cannot be inspected; without it,
    queued jobs are sent again after `requeue_after_seconds`."""

    def __init__(self, settings: WorkerSettings, send: Callable[[str], None], *,
                 store: JobStore | None = None, blobs: BlobStore | None = None,
                 interval: float | None = None, held: HeldJobs | None = None):
        self.settings, self.send, self.held = settings, send, held
        self.store = store or JobStore(settings.database)
        self.blobs = blobs or open_store(settings.storage, endpoint_url=settings.s3_endpoint_url,
                                         region=settings.s3_region)
        self.interval = interval if interval is not None else max(settings.lease_seconds / 4, 1.0)
        self._next_check = 0.0
        """When (time.monotonic) the broker is looked into next."""
        # A pass at once (what a worker killed before this start left: scratch folders, jobs
        # to send), then every `interval`.
        self._periodic = Periodic(self.sweep, self.interval, name="dgs-sweeper", log=log,
                                  what="sweep", at_once=True)

    def sweep(self) -> dict[str, list[str]]:
        """One pass: re-sent job ids, expired objects, removed scratch folders."""
        s = self.settings
        held, requeue_after = None, s.requeue_after_seconds
        due = time.monotonic() >= self._next_check
        # A worker claims a job the moment it takes its message; one that has not after a
        # lease (it is presumed dead by then anyway) or a check interval lost it.
        grace = max(s.lost_message_seconds, s.lease_seconds)
        if self.held is not None:
            requeue_after = None
            if due:
                try:
                    held = self.held(grace)
                except Exception as exc:  # the broker is briefly away: at the next pass
                    log.warning("could not look into the broker (%s: %s); trying again in "
                                "%.0f s", type(exc).__name__, exc, self.interval)
                    due = False
                else:
                    if held is None:  # this broker cannot be inspected: the age rule
                        requeue_after = s.requeue_after_seconds
        sent = self.store.redispatch_stranded(self.send, held=held, grace=grace,
                                              requeue_after=requeue_after,
                                              min_gap=s.lease_seconds)
        for job_id, why in sent.items():
            log.warning("job %s: sent to the queue again: %s", job_id, why)
        cleaned, uncached = [], []
        if due:
            self._next_check = time.monotonic() + s.lost_message_seconds
            cleaned = clean_job_folders(self.store, s.scratch)
            uncached = clean_capture_folders(self.store, s.scratch, s.capture_cache_seconds)
        return {"redispatched": list(sent), "scratch": cleaned, "capture_copies": uncached,
                **self.expire()}

    def expire(self) -> dict[str, list[str]]:
        """Delete jobs (finished ones no active job renders from), captures (no active job on
        them) and assets (no active job uses them: a render's envmap, a reconstruction's
        normal model) whose expires_at has passed, with their files."""
        now = utcnow()
        out: dict[str, list[str]] = {"jobs": [], "captures": [], "assets": []}
        with self.store.session() as s:
            active = list(s.execute(select(Job.capture_id, Job.source_job_id, Job.params)
                                    .where(Job.state.in_(ACTIVE))))
            busy = {row.capture_id for row in active}
            needed = {row.source_job_id for row in active}
            used = {asset for row in active for asset in assets_named(row.params)}
            jobs = [j for j in s.scalars(select(Job).where(Job.expires_at < now,
                                                           Job.state.in_(TERMINAL)))
                    if j.id not in needed]
            captures = [c for c in s.scalars(select(Capture).where(Capture.expires_at < now))
                        if c.id not in busy]
            assets = [a for a in s.scalars(select(Asset).where(Asset.expires_at < now))
                      if a.id not in used]
            for job in jobs:
                for each in [job.id, *delete_parts(s, job.id)]:
                    self.blobs.delete_prefix(f"jobs/{each}")
                    shutil.rmtree(self.settings.scratch / "jobs" / each, ignore_errors=True)
                s.execute(update(Job).where(Job.source_job_id == job.id)
                          .values(source_job_id=None))
                s.delete(job)
                out["jobs"].append(job.id)
            for cap in captures:
                self.blobs.delete_prefix(f"captures/{cap.id}")
                shutil.rmtree(self.settings.data_dir / "uploads" / cap.id, ignore_errors=True)
                s.execute(update(Job).where(Job.capture_id == cap.id).values(capture_id=None))
                s.delete(cap)
                out["captures"].append(cap.id)
            for asset in assets:
                self.blobs.delete_prefix(f"assets/{asset.id}")
                s.delete(asset)
                out["assets"].append(asset.id)
            forget_expired(s)  # idempotency keys: rows only, nothing to log
        for kind, ids in out.items():
            for obj in ids:
                log.warning("%s %s expired (expires_at passed): deleted with its files", kind[:-1],
                            obj)
        return out

    def start(self) -> Sweeper:
        self._periodic.start()
        return self

    def stop(self) -> None:
        self._periodic.stop()
