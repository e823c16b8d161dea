"""Runs one job in a worker process: claim the lease, hand the job to its pipeline's execution
(`worker.reconstruct_job`, `worker.relight_job`), record the outcome (succeeded, failed with a
code, cancelled, or released back to the queue when this worker shuts down).

What the executions share lives here: fetching a capture from the store once per machine, and
publishing a folder's files as typed artifacts under jobs/<id>/artifacts/.
"""

from __future__ import annotations

import ctypes
import gc
import shutil
import signal
import threading
import traceback
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import core  # noqa: F401  (first: OpenMP's passive wait is set before torch loads it)
import torch
from billiard.exceptions import SoftTimeLimitExceeded
from pydantic import ValidationError

from core.data.headers import set_default_max_pixels
from core.files import sha256_file
from core.rundir import classify
from worker.assemble_job import AssembleJob
from worker.blobs import BlobStore, open_store
from worker.execution import Execution, JobStopped
from worker.faults import hang_if_asked
from worker.gate import nothing_to_run
from worker.models import Job
from worker.pipelines import get_pipeline
from worker.progress import JobLink, log_line
from worker.redact import SERVER, redact
from worker.scratch import capture_folder, hold_capture, job_folder, mark
from worker.settings import WorkerSettings
from worker.store import JobStore, Owner

__all__ = ["Outcome", "Runner"]


@dataclass(frozen=True)
class Outcome:
    status: str
    """What happened: succeeded, failed, cancelled, released (back in the queue: this worker
    is shutting down), lost (lease taken away), or, for a message that found nothing to do,
    leased (another live worker runs the job), terminal (it has ended), missing (deleted),
    exhausted (the redelivery cap was reached: the job failed)."""
    note: str = ""
    """Why nothing was done, for the worker's log."""
    gave_way: bool = False
    """Released because it gave its worker to another tenant's job (`worker.fair`): the pool
    process may run that job itself (`worker.tasks`)."""


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


def _release_memory() -> None:
    """After a job, before this pool process takes the next or waits idle (it runs several,
    worker.celery_app): what the job left in reference cycles is freed, the C heap's free pages
    go back to the system (glibc keeps them otherwise: 4 GiB of freed tensors stayed resident,
    222 MiB after the trim), and on a GPU the cached blocks go back to the device, so the next
    job, or another worker's on the same GPU, finds them free."""
    gc.collect()
    if _LIBC is not None:
        _LIBC.malloc_trim(0)
    if torch.cuda.is_initialized():
        torch.cuda.empty_cache()


def _glibc() -> ctypes.CDLL | None:
    try:
        libc = ctypes.CDLL(None)
        return libc if hasattr(libc, "malloc_trim") else None
    except OSError:  # no C library to load by that name (not glibc): nothing to trim
        return None


_LIBC = _glibc()


class Runner:
    """Runs jobs from the job store with the settings' storage."""

    def __init__(self, settings: WorkerSettings, store: JobStore | None = None,
                 blobs: BlobStore | None = None):
        set_default_max_pixels(settings.max_image_pixels)  # every image core decodes here
        if settings.torch_threads is not None:  # N workers on one machine share its cores
            torch.set_num_threads(settings.torch_threads)
        self.settings = settings
        self.store = store or JobStore(settings.database)
        self.blobs = blobs or open_store(settings.storage, endpoint_url=settings.s3_endpoint_url,
                                         region=settings.s3_region)
        self._published: dict[str, tuple[int, int]] = {}
        """Artifact paths already published, with the (size, mtime) their file had."""
        self._handed = False
        self._holds: list = []
        """The cached captures the running job holds (`worker.scratch.hold_capture`)."""

    def run(self, job_id: str, *, handed: bool = False) -> Outcome:
        """Claim and run the job. A message for a job that another live worker runs, that has
        ended or was deleted (a duplicate delivery: a sweeper re-sent it, the broker delivered
        it twice) finds nothing to do and is dropped: if the running worker dies, its lease
        expires and a sweeper sends the job again. `handed`: the job was handed to this pool
        process after its own job gave way (`worker.tasks`), so the time limit it may reach is
        that task's: reaching it sends the job back to the queue instead of failing it."""
        self._handed = handed
        s = self.settings
        if not handed and self.store.gives_way_at_start(
                job_id, share_after=s.share_after_seconds, starting_seconds=s.stall_seconds):
            self.store.append_logs(job_id, [log_line(
                "another tenant came to wait with fewer jobs on the workers while this job's "
                "worker started: its turn goes to that tenant's job; back in the queue (fair "
                "share)")])
            return Outcome("released", "another tenant came to wait while this pool process "
                           "started: its turn goes to that tenant's job (fair share), and it "
                           "goes back to the queue", gave_way=True)
        owner = Owner.current()
        claim = self.store.claim(job_id, owner, s.lease_seconds, s.max_attempts)
        if claim.status != "claimed":
            return Outcome(claim.status, nothing_to_run(claim))
        mark(s.scratch, job_id, owner)
        link = JobLink(self.store, claim.job, owner, s).start()
        outer, self._holds = self._holds, []  # an assembly runs inside its last part's run
        try:
            with _stop_on_sigterm(link):
                outcome = self._execute(claim.job, link)
        finally:
            link.close()
            for held in self._holds:
                held.close()
            self._holds = outer
            _release_memory()
        if outcome.status in ("succeeded", "failed", "cancelled"):
            shutil.rmtree(job_folder(s.scratch, job_id), ignore_errors=True)
        if outcome.status == "succeeded" and claim.job.parent_id is not None:
            self._assemble(claim.job.parent_id)
        return outcome

    def _assemble(self, parent_id: str) -> None:
        """The last part of a parted job has succeeded here: assemble the job at once, in this
        process (no round trip through the broker), under the job's own claim and lease. If
        this worker dies meanwhile, the job's lease lapses and a sweeper sends it to another;
        if a sweeper sent it already and another worker took it, the claim says so."""
        parent = self.store.get(parent_id)
        if parent is not None and parent.stage == "assembling" and parent.lease_owner is None:
            self.run(parent_id, handed=self._handed)

    def _execution(self, job: Job, link: JobLink) -> Execution:
        pipeline = get_pipeline(job.pipeline)
        params = pipeline.parse(job.params)
        if job.parts:  # a job run as parts: what is left of it is their assembly
            return AssembleJob(self, job, params, link)
        return pipeline.execution_class()(self, job, params, link)

    def _execute(self, job: Job, link: JobLink) -> Outcome:
        link.log(f"attempt {job.attempts} on {link.owner.host} (pid {link.owner.pid})")
        hang_if_asked("claimed")
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
        if (link.shutdown or link.yielding) and not link.cancelled:
            why = ("its worker shut down" if link.shutdown else
                   "it gave its worker to another tenant's job (fair share)")
            return self._release(job, link, f"{why}: {reason}", f"{why} at {exc.where}",
                                 gave_way=not link.shutdown)
        link.log(f"cancelled: {reason}")
        link.close()
        self.store.finish(job.id, link.owner, "cancelled", None,
                          f"cancelled; {execution.retry_note}")
        return Outcome("cancelled")

    def _release(self, job: Job, link: JobLink, logged: str, why: str, *,
                 gave_way: bool = False) -> Outcome:
        """Give the claimed job back to the queue (no attempt counted): `logged` goes to its
        log, `why` to its message."""
        link.log(f"{logged}; back in the queue")
        link.close()
        self.store.release(job.id, link.owner, f"back in the queue: {why}")
        return Outcome("released", gave_way=gave_way)

    def _fail(self, job: Job, link: JobLink, exc: Exception, retry_note: str) -> Outcome:
        if isinstance(exc, SoftTimeLimitExceeded) and self._handed:
            why = "its pool process reached its time limit (it ran another job first)"
            return self._release(job, link, f"{why}, to resume from its last checkpoint", why)
        roots = self._client_roots(job, link)  # what a failure's message may name
        if isinstance(exc, SoftTimeLimitExceeded):
            error = {"code": "time_limit", "retryable": True,
                     "message": f"the job reached its time limit; {retry_note}"}
        elif isinstance(exc, (ValueError, ValidationError)):  # CaptureError is a ValueError
            error = {"code": "invalid_input", "retryable": False,
                     "message": redact(str(exc).replace("\n", " "), roots)[:2000]}
        else:
            error = {"code": "internal", "retryable": True,
                     "message": redact(f"{type(exc).__name__}: {exc}", roots)[:2000]}
            for line in traceback.format_exc().splitlines():
                link.log(redact(line, roots))
        link.log(f"failed: {error['message']}")
        link.close()
        self.store.finish(job.id, link.owner, "failed", error, error["message"][:512])
        return Outcome("failed")

    def _client_roots(self, job: Job, link: JobLink) -> list[tuple[Path | None, str]]:
        """How the folders of this machine that a failure may name are shown to the client
        (worker.redact): files of the capture relative to it, the job's own folders
        relative to them, anything else of the data or scratch folder as <server>."""
        s, scratch = self.settings, self.settings.scratch
        jobs = scratch / "jobs" / job.id
        roots: list[tuple[Path | None, str]] = [
            (jobs / "run", ""), (jobs / f"relight-{link.owner.token}" / "envmap", ""),
            (jobs / f"relight-{link.owner.token}", ""), (jobs, ""),
            (scratch, SERVER), (s.data_dir, SERVER)]
        if job.capture_id is not None:
            roots += [(self.blobs.local_path(f"captures/{job.capture_id}"), ""),
                      (capture_folder(scratch, job.capture_id), "")]
        return roots

    # -- inputs -------------------------------------------------------------------------------
    def capture(self, job: Job, link: JobLink) -> Path:
        """The capture's folder on this machine (fetched from the store once per machine, by one
        process while the others wait), held until the job ends (`worker.scratch`)."""
        if job.capture_id is None:
            raise ValueError("capture: the job's capture was deleted")
        prefix = f"captures/{job.capture_id}"
        local = self.blobs.local_path(prefix)
        if local is not None:
            if not (local / "capture.json").is_file():
                raise ValueError(f"capture: {job.capture_id} is not in the store")
            return local

        def fetch(folder: Path) -> None:
            blobs = self.blobs.list(prefix)
            if not blobs:
                raise ValueError(f"capture: {job.capture_id} is not in the store")
            link.update(fraction=0.0, stage="fetching capture",
                        message=f"{len(blobs)} files, {sum(b.size for b in blobs) / 1e6:.0f} MB")
            for i, blob in enumerate(blobs):
                if link.should_stop():  # a cancel, a shutdown: not after the whole download
                    raise JobStopped(f"fetching the capture ({i} of {len(blobs)} files)")
                self.blobs.get_file(blob.key, folder / blob.key[len(prefix) + 1:])

        cache = capture_folder(self.settings.scratch, job.capture_id)
        # held until the job ends: the sweeper deletes no capture a job holds
        self._holds.append(hold_capture(cache, fetch))
        return cache

    def fetch(self, prefix: str, dest: Path) -> list[Path]:
        """Every blob under `prefix` into `dest`, keeping the layout below the prefix."""
        out = []
        for blob in self.blobs.list(prefix):
            out.append(dest / blob.key[len(prefix) + 1:])
            self.blobs.get_file(blob.key, out[-1])
        return out

    # -- outputs ------------------------------------------------------------------------------
    def mark_published(self, root: Path) -> None:
        """Count every file under `root` (fetched from the job's artifacts, laid out as they
        are) as published, so that `publish` sends only what changes after."""
        for path in root.rglob("*"):
            if path.is_file():
                stat = path.stat()
                self._published[path.relative_to(root).as_posix()] = (
                    stat.st_size, stat.st_mtime_ns)

    def publish(self, job: Job | str, root: Path, prefix: str = "", *,
                frames: bool | None = None) -> int:
        """Copy new or changed files under `root` to jobs/<id>/artifacts/<prefix><path> (`job`:
        the job or its id) and record them with their kind (what `classify` does not know,
        such as checkpoints, stays out); `frames` True publishes only the files of a frame,
        False only the others. Returns how many were published."""
        job_id = job if isinstance(job, str) else job.id
        published = 0
        for path in sorted(p for p in root.rglob("*") if p.is_file()):
            rel = prefix + path.relative_to(root).as_posix()
            kind = classify(rel)
            stat = path.stat()
            if kind is None or self._published.get(rel) == (stat.st_size, stat.st_mtime_ns):
                continue
            if frames is not None and frames != (kind.frame is not None):
                continue
            digest = sha256_file(path)
            self.blobs.put_file(f"jobs/{job_id}/artifacts/{rel}", path)
            self.store.add_artifact(job_id, rel, kind=kind.kind, size=stat.st_size,
                                    sha256=digest, content_type=kind.content_type,
                                    frame=kind.frame)
            self._published[rel] = (stat.st_size, stat.st_mtime_ns)
            published += 1
        return published
