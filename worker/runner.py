"""Runs one job in a worker process: claim the lease, hand the job to its pipeline's execution
(`worker.reconstruct_job`, `worker.relight_job`), record the outcome (succeeded, failed with a
code, cancelled, or released back to the queue when this worker shuts down).

What the executions share lives here: fetching a capture from the store once per machine, and
publishing a folder's files as typed artifacts under jobs/<id>/artifacts/.
"""

from __future__ import annotations

import hashlib
import shutil
import signal
import threading
import traceback
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from typing import Protocol

from worker.artifacts import classify
from worker.blobs import BlobStore, open_store
from worker.models import Job
from worker.pipelines import get_pipeline
from worker.progress import JobLink
from worker.settings import WorkerSettings
from worker.store import JobStore, Owner

__all__ = ["Execution", "JobStopped", "Outcome", "Runner"]


@dataclass(frozen=True)
class Outcome:
    status: str
    """What happened: succeeded, failed, cancelled, released (back in the queue: this worker
    is shutting down), lost (lease taken away), leased, terminal, missing, exhausted."""
    retry_in: float | None = None
    """Seconds after which the task should try again (another worker holds the lease)."""


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class JobStopped(Exception):
    """An execution stopped between two steps because `link.should_stop()` said so (a cancel,
    a lost lease, this worker shutting down); `where` says where, for the log."""

    def __init__(self, where: str):
        super().__init__(f"stopped at {where}")
        self.where = where


class Execution(Protocol):
    """One job of one pipeline, run by `Runner`: `run()` does the work and publishes it, or
    raises JobStopped, ValueError (bad input: the job fails with invalid_input) or anything
    else (internal, retryable)."""

    retry_note: str
    """What a retry of a cancelled job does, for its message."""

    def run(self) -> None: ...


@contextmanager
def _stop_on_sigterm(link: JobLink):
    """While a job runs in this process's main thread, SIGTERM (a worker shutting down, a
    container stopped) makes it stop at its next step with a checkpoint instead of dying."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame) -> None:
        link.shutdown = True
        link.stop.set()

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class Runner:
    """Runs jobs from the job store with the settings' storage."""

    def __init__(self, settings: WorkerSettings, store: JobStore | None = None,
                 blobs: BlobStore | None = None):
        self.settings = settings
        self.store = store or JobStore(settings.database)
        self.blobs = blobs or open_store(settings.storage, endpoint_url=settings.s3_endpoint_url,
                                         region=settings.s3_region)
        self._published: dict[str, tuple[int, int]] = {}
        """Artifact paths already published, with the (size, mtime) their file had."""

    def run(self, job_id: str) -> Outcome:
        s = self.settings
        owner = Owner.current()
        claim = self.store.claim(job_id, owner, s.lease_seconds, s.max_attempts)
        if claim.status == "leased":
            return Outcome("leased", retry_in=max(1.0, min(claim.retry_in + 1.0, s.lease_seconds)))
        if claim.status != "claimed":
            return Outcome(claim.status)
        link = JobLink(self.store, claim.job, owner, s).start()
        try:
            with _stop_on_sigterm(link):
                return self._execute(claim.job, link)
        finally:
            link.close()

    def _execution(self, job: Job, link: JobLink) -> Execution:
        from worker.export_job import ExportJob
        from worker.reconstruct_job import ReconstructJob
        from worker.relight_job import RelightJob

        pipeline = get_pipeline(job.pipeline)
        params = pipeline.params.model_validate(job.params)
        kinds = {"reconstruct": ReconstructJob, "relight": RelightJob, "export": ExportJob}
        return kinds[pipeline.name](self, job, params, link)

    def _execute(self, job: Job, link: JobLink) -> Outcome:
        link.log(f"attempt {job.attempts} on {link.owner.host} (pid {link.owner.pid})")
        execution = None
        try:
            execution = self._execution(job, link)
            execution.run()
        except JobStopped as exc:
            return self._stopped(job, link, exc, execution)
        except Exception as exc:
            note = execution.retry_note if execution is not None else "retry runs it again"
            return self._fail(job, link, exc, note)
        link.update(fraction=1.0, stage="done", message="")
        link.close()
        self.store.finish(job.id, link.owner, "succeeded", None, "")
        return Outcome("succeeded")

    def _stopped(self, job: Job, link: JobLink, exc: JobStopped,
                 execution: Execution) -> Outcome:
        if link.lost:
            link.log("lease lost to another worker; stopping without writing")
            return Outcome("lost")
        reason = exc.__cause__ or exc  # core's own words: "stopped at step 57 of frame ..."
        if link.shutdown and not link.cancelled:
            link.log(f"worker shutting down: {reason}; back in the queue")
            link.close()
            self.store.release(job.id, link.owner, "back in the queue: its worker shut "
                               f"down at {exc.where}")
            return Outcome("released")
        link.log(f"cancelled: {reason}")
        link.close()
        self.store.finish(job.id, link.owner, "cancelled", None,
                          f"cancelled; {execution.retry_note}")
        return Outcome("cancelled")

    def _fail(self, job: Job, link: JobLink, exc: Exception, retry_note: str) -> Outcome:
        from billiard.exceptions import SoftTimeLimitExceeded
        from pydantic import ValidationError

        if isinstance(exc, SoftTimeLimitExceeded):
            error = {"code": "time_limit", "retryable": True,
                     "message": f"the job reached its time limit; {retry_note}"}
        elif isinstance(exc, (ValueError, ValidationError)):  # CaptureError is a ValueError
            error = {"code": "invalid_input", "retryable": False,
                     "message": str(exc).replace("\n", " ")[:2000]}
        else:
            error = {"code": "internal", "retryable": True,
                     "message": f"{type(exc).__name__}: {exc}"[:2000]}
            for line in traceback.format_exc().splitlines():
                link.log(line)
        link.log(f"failed: {error['message']}")
        link.close()
        self.store.finish(job.id, link.owner, "failed", error, error["message"][:512])
        return Outcome("failed")

    # -- inputs -------------------------------------------------------------------------------
    def capture(self, job: Job, link: JobLink) -> Path:
        """The capture's folder on this machine (fetched from the store once per machine)."""
        if job.capture_id is None:
            raise ValueError("capture: the job's capture was deleted")
        prefix = f"captures/{job.capture_id}"
        local = self.blobs.local_path(prefix)
        if local is not None:
            if not (local / "capture.json").is_file():
                raise ValueError(f"capture: {job.capture_id} is not in the store")
            return local
        cache = self.settings.scratch / "captures" / job.capture_id
        if (cache / ".complete").is_file():
            return cache
        blobs = self.blobs.list(prefix)
        if not blobs:
            raise ValueError(f"capture: {job.capture_id} is not in the store")
        link.update(fraction=0.0, stage="fetching capture",
                    message=f"{len(blobs)} files, {sum(b.size for b in blobs) / 1e6:.0f} MB")
        for blob in blobs:
            self.blobs.get_file(blob.key, cache / blob.key[len(prefix) + 1:])
        (cache / ".complete").touch()
        return cache

    def fetch(self, prefix: str, dest: Path) -> list[Path]:
        """Every blob under `prefix` into `dest`, keeping the layout below the prefix."""
        out = []
        for blob in self.blobs.list(prefix):
            out.append(dest / blob.key[len(prefix) + 1:])
            self.blobs.get_file(blob.key, out[-1])
        return out

    # -- outputs ------------------------------------------------------------------------------
    def publish(self, job: Job, root: Path, prefix: str = "") -> int:
        """Copy new or changed files under `root` to jobs/<id>/artifacts/<prefix><path> and
        record them with their kind (what `classify` does not know, such as checkpoints, stays
        out); returns how many were published."""
        published = 0
        for path in sorted(p for p in root.rglob("*") if p.is_file()):
            rel = prefix + path.relative_to(root).as_posix()
            kind = classify(rel)
            stat = path.stat()
            if kind is None or self._published.get(rel) == (stat.st_size, stat.st_mtime_ns):
                continue
            digest = sha256_of(path)
            self.blobs.put_file(f"jobs/{job.id}/artifacts/{rel}", path)
            self.store.add_artifact(job.id, rel, kind=kind.kind, size=stat.st_size,
                                    sha256=digest, content_type=kind.content_type,
                                    frame=kind.frame)
            self._published[rel] = (stat.st_size, stat.st_mtime_ns)
            published += 1
        return published
