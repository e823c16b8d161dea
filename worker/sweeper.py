"""Housekeeping that keeps the queue honest: re-send jobs whose worker was lost, and delete what
has expired (explicit `expires_at` only; every deletion is logged).

A worker killed outright (SIGKILL of the whole worker, a machine gone) may take its broker
message with it: the SQLite transport hides a delivered message until it is acknowledged, Redis
until its visibility timeout (days). The job store knows better: a running job whose lease has
expired has no worker. The sweeper sends such jobs to the broker again; the lease makes a
duplicate message harmless. Any number of sweepers may run (API processes, workers):
`JobStore.mark_dispatched` lets one of them send.
"""

from __future__ import annotations

import logging
import shutil
import threading
from collections.abc import Callable

from sqlalchemy import select, update

from worker.blobs import BlobStore, open_store
from worker.models import Asset, Capture, Job, utcnow
from worker.settings import WorkerSettings
from worker.store import ACTIVE, TERMINAL, JobStore

__all__ = ["Sweeper"]

log = logging.getLogger("dgs.sweeper")


class Sweeper:
    """`sweep()` once, or `start()` a daemon thread that sweeps every `interval` seconds."""

    def __init__(self, settings: WorkerSettings, send: Callable[[str], None], *,
                 store: JobStore | None = None, blobs: BlobStore | None = None,
                 interval: float | None = None):
        self.settings, self.send = settings, send
        self.store = store or JobStore(settings.database)
        self.blobs = blobs or open_store(settings.storage, endpoint_url=settings.s3_endpoint_url,
                                         region=settings.s3_region)
        self.interval = interval if interval is not None else max(settings.lease_seconds / 4, 1.0)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def sweep(self) -> dict[str, list[str]]:
        """One pass: re-sent job ids and expired objects."""
        s = self.settings
        sent = self.store.redispatch_stranded(self.send, requeue_after=s.requeue_after_seconds,
                                              min_gap=s.lease_seconds)
        for job_id in sent:
            log.warning("job %s: its worker is gone; sent to the queue again", job_id)
        return {"redispatched": sent, **self.expire()}

    def expire(self) -> dict[str, list[str]]:
        """Delete jobs (finished ones no active job renders from), captures (no active job on
        them) and assets (no active job renders with them) whose expires_at has passed, with
        their files."""
        now = utcnow()
        out: dict[str, list[str]] = {"jobs": [], "captures": [], "assets": []}
        with self.store.session() as s:
            active = list(s.execute(select(Job.capture_id, Job.source_job_id, Job.pipeline,
                                           Job.params).where(Job.state.in_(ACTIVE))))
            busy = {row.capture_id for row in active}
            needed = {row.source_job_id for row in active}
            envmaps = {(row.params or {}).get("envmap") for row in active
                       if row.pipeline == "relight"}
            jobs = [j for j in s.scalars(select(Job).where(Job.expires_at < now,
                                                           Job.state.in_(TERMINAL)))
                    if j.id not in needed]
            captures = [c for c in s.scalars(select(Capture).where(Capture.expires_at < now))
                        if c.id not in busy]
            assets = [a for a in s.scalars(select(Asset).where(Asset.expires_at < now))
                      if a.id not in envmaps]
            for job in jobs:
                self.blobs.delete_prefix(f"jobs/{job.id}")
                shutil.rmtree(self.settings.scratch / "jobs" / job.id, ignore_errors=True)
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
        for kind, ids in out.items():
            for obj in ids:
                log.warning("%s %s expired (expires_at passed): deleted with its files", kind[:-1],
                            obj)
        return out

    def start(self) -> Sweeper:
        self._thread = threading.Thread(target=self._loop, name="dgs-sweeper", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)

    def _loop(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                self.sweep()
            except Exception:  # the database or broker is briefly away: try at the next pass
                log.exception("sweep failed; retrying in %.0f s", self.interval)
