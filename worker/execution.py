"""What a job's execution is to the runner (`worker.runner.Runner`): an object whose `run()`
does the work and publishes it, and the exception it raises when told to stop between two
steps."""

from __future__ import annotations

from typing import Protocol

__all__ = ["Execution", "JobStopped"]


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
