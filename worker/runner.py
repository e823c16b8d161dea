"""Runs one job in a worker process: claim the lease, fetch the capture, resume the run directory
from its last checkpoint, call the core pipeline, publish artifacts, record the outcome.

A job's run directory lives in the worker's scratch folder (<scratch>/jobs/<id>/run). Every
checkpoint is also copied to the store (jobs/<id>/state/) and every finished frame published as
artifacts as soon as it is written, so that a worker on another machine (another scratch folder)
resumes where a lost one stopped.
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

from worker.artifacts import classify
from worker.blobs import BlobStore, open_store
from worker.models import Job
from worker.pipelines import get_pipeline
from worker.progress import JobLink
from worker.settings import WorkerSettings
from worker.store import JobStore, Owner

__all__ = ["Outcome", "Runner"]

# Share of a frame's progress taken by training; the rest is its renders and PLY.
TRAIN_SHARE = 0.97
# Share of the whole job left for publishing artifacts at the end.
PUBLISH_SHARE = 0.01
STAGES = {0: "starting", 1: "appearance", 2: "geometry", 3: "occlusion"}


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
        """Run-directory files already published, with the (size, mtime) they had."""

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

    def _execute(self, job: Job, link: JobLink) -> Outcome:
        from core.pipeline import Stopped

        link.log(f"attempt {job.attempts} on {link.owner.host} (pid {link.owner.pid})")
        try:
            pipeline = get_pipeline(job.pipeline)
            params = pipeline.params.model_validate(job.params)
            capture = self._capture(job, link)
            run = self._run_dir(job, link)
            self._reconstruct(job, params, capture, run, link)
            self._evaluate(run, capture, link)
            self._publish(job, run, link, final=True)
        except Stopped as exc:
            if link.lost:
                link.log("lease lost to another worker; stopping without writing")
                return Outcome("lost")
            if link.shutdown and not link.cancelled:
                link.log(f"worker shutting down: {exc}; back in the queue")
                link.close()
                self.store.release(job.id, link.owner, "back in the queue: its worker shut "
                                   f"down at step {exc.step}")
                return Outcome("released")
            link.log(f"cancelled: {exc}")
            link.close()
            self.store.finish(job.id, link.owner, "cancelled", None,
                              "cancelled; retry resumes from the last checkpoint")
            return Outcome("cancelled")
        except Exception as exc:
            return self._fail(job, link, exc)
        link.update(fraction=1.0, stage="done", message="")
        link.close()
        self.store.finish(job.id, link.owner, "succeeded", None, "")
        return Outcome("succeeded")

    def _fail(self, job: Job, link: JobLink, exc: Exception) -> Outcome:
        from billiard.exceptions import SoftTimeLimitExceeded
        from pydantic import ValidationError

        if isinstance(exc, SoftTimeLimitExceeded):
            error = {"code": "time_limit", "retryable": True,
                     "message": "the job reached its time limit; retry resumes from the last "
                                "checkpoint"}
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
    def _capture(self, job: Job, link: JobLink) -> Path:
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

    def _run_dir(self, job: Job, link: JobLink) -> Path:
        """<scratch>/jobs/<id>/run, restored from jobs/<id>/state/ and the published frames
        when this machine does not have it (a job resumed elsewhere)."""
        run = self.settings.scratch / "jobs" / job.id / "run"
        if (run / "config.json").is_file():
            return run
        state = self.blobs.list(f"jobs/{job.id}/state")
        if state:
            link.log(f"restoring the run directory from the store ({len(state)} files)")
            base = f"jobs/{job.id}/state/"
            for blob in state:
                self.blobs.get_file(blob.key, run / blob.key[len(base):])
            base = f"jobs/{job.id}/artifacts/"
            for blob in self.blobs.list(f"jobs/{job.id}/artifacts/frames"):
                self.blobs.get_file(blob.key, run / blob.key[len(base):])
        return run

    # -- the work -----------------------------------------------------------------------------
    def _reconstruct(self, job: Job, params, capture: Path, run: Path, link: JobLink) -> None:
        from core.pipeline import Progress, reconstruct

        overrides = dict(params.config)
        if params.checkpoint_every is not None:
            overrides["checkpoint_every"] = params.checkpoint_every
        resume = (run / "config.json").is_file()
        if resume:
            link.log("resuming from the run directory's last checkpoint")
        run.parent.mkdir(parents=True, exist_ok=True)
        last_logged = [-1]

        def on_progress(event: Progress) -> None:
            step_share = TRAIN_SHARE * event.step / max(event.iterations, 1)
            if event.kind == "frame_done":
                step_share = 1.0
            fraction = (event.frame_index + step_share) / event.frames * (1 - PUBLISH_SHARE)
            stage = ("outputs" if event.step >= event.iterations else event.phase
                     if event.phase != "key" else STAGES.get(event.stage, ""))
            link.update(fraction=fraction, stage=stage, frame=event.frame_index + 1,
                        frames=event.frames, iteration=event.step, iterations=event.iterations,
                        message=f"frame {event.frame} ({event.gaussians} Gaussians)")
            if event.kind == "frame_start":
                link.log(f"frame {event.frame} ({event.frame_index + 1}/{event.frames}) from "
                         f"step {event.step}")
            elif event.kind == "step" and event.step // 100 != last_logged[0]:
                last_logged[0] = event.step // 100
                link.log(f"frame {event.frame} step {event.step}/{event.iterations} stage "
                         f"{event.stage} loss {event.loss:.4f} gaussians {event.gaussians}")
            elif event.kind == "checkpoint":
                self._save_state(job, run, Path(event.path))
            elif event.kind == "frame_done":
                link.log(f"frame {event.frame} done")
                self._publish(job, run, link, final=False)
                self._save_state(job, run, None)

        reconstruct(capture, run, preset=params.preset, frames=params.frames, gop=params.gop,
                    overrides=overrides or None, resume=resume, progress=False,
                    on_progress=on_progress, should_stop=link.should_stop)

    def _evaluate(self, run: Path, capture: Path, link: JobLink) -> None:
        from core.evaluate import evaluate_run

        link.update(fraction=1 - PUBLISH_SHARE, stage="evaluating", message="")
        try:
            result = evaluate_run(run, capture)
        except ValueError as exc:  # e.g. no held-out camera: the job still succeeds
            link.log(f"evaluation skipped: {exc}")
            return
        psnr = result.get("psnr")
        link.log(f"held-out views: PSNR {psnr:.2f} dB" if psnr is not None else
                 "held-out views evaluated")

    # -- outputs ------------------------------------------------------------------------------
    def _save_state(self, job: Job, run: Path, checkpoint: Path | None) -> None:
        """Copy what a resume needs (config, metrics, this checkpoint) to jobs/<id>/state/."""
        files = [run / "config.json", run / "metrics.json"]
        if checkpoint is not None:
            files.append(checkpoint)
        for path in files:
            if path.is_file():
                self.blobs.put_file(f"jobs/{job.id}/state/{path.relative_to(run).as_posix()}",
                                    path)

    def _publish(self, job: Job, run: Path, link: JobLink, *, final: bool) -> None:
        """Copy new or changed outputs of the run directory to jobs/<id>/artifacts/ and record
        them (checkpoints stay out)."""
        if final:
            link.update(fraction=1 - PUBLISH_SHARE / 2, stage="publishing", message="")
        published = 0
        for path in sorted(p for p in run.rglob("*") if p.is_file()):
            rel = path.relative_to(run).as_posix()
            kind = classify(rel)
            stat = path.stat()
            if kind is None or self._published.get(rel) == (stat.st_size, stat.st_mtime_ns):
                continue
            digest = sha256_of(path)
            key = f"jobs/{job.id}/artifacts/{rel}"
            self.blobs.put_file(key, path)
            self.store.add_artifact(job.id, rel, kind=kind.kind, size=stat.st_size,
                                    sha256=digest, content_type=kind.content_type,
                                    frame=kind.frame)
            self._published[rel] = (stat.st_size, stat.st_mtime_ns)
            published += 1
        if final:
            link.log(f"published {published} artifacts")
            # Everything is in the store now; a finished job is never resumed.
            self.blobs.delete_prefix(f"jobs/{job.id}/state")
            shutil.rmtree(run.parent, ignore_errors=True)
