"""What a job's execution and the runner (`worker.runner.Runner`) are to each other: an
execution is an object whose `run()` does the work and publishes it, raising `JobStopped` when
told to stop between two steps; the runner is, to an execution, a `Host` (the settings, the
stores, a capture on this machine, publishing). The runner knows the executions; they know only
this module."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

from worker.blobs import BlobStore
from worker.models import Job
from worker.progress import JobLink
from worker.settings import WorkerSettings
from worker.store import JobStore

__all__ = ["Execution", "Host", "JobStopped"]


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


class Host(Protocol):
    """What an execution uses of the runner that runs it."""

    settings: WorkerSettings
    store: JobStore
    blobs: BlobStore

    def capture(self, job: Job, link: JobLink) -> Path:
        """The job's capture folder on this machine (fetched once per machine)."""
        ...

    def fetch(self, prefix: str, dest: Path) -> list[Path]:
        """Every blob under `prefix` into `dest`."""
        ...

    def publish(self, job: Job | str, root: Path, prefix: str = "", *,
                frames: bool | None = None) -> int:
        """New or changed files under `root` as the job's artifacts; how many."""
        ...

    def mark_published(self, root: Path) -> None:
        """Count every file under `root` as published already (fetched from the artifacts)."""
        ...
