"""A running job's link to the job store: a heartbeat thread that renews the lease and writes the
latest progress and log lines every `heartbeat_seconds`, and between heartbeats looks (a read,
every `watch_seconds`) for a cancel or another tenant's turn (worker.fair).

The training loop only updates in-memory state (`update`, `log`) and asks `should_stop()` after
each step, so it never waits on the database. Updates between two heartbeats are coalesced into
one progress event, except milestones (a frame's start and end, any change of frame): each of
those becomes an event of its own, however fast the frames go. A cancel (or a lost lease) sets
the stop flag; the loop then stops at its next step. If it has not stopped
`cancel_grace_seconds` later (a long native call), the heartbeat thread records the cancel and
ends its own process: the worker is freed within seconds either way.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from typing import Any

from worker.fair import yield_wait
from worker.models import Job
from worker.settings import WorkerSettings
from worker.store import JobStore, Owner

__all__ = ["JobLink", "log_line"]


def log_line(text: str) -> str:
    """A line of a job's log as stored: the worker's local time, then the text."""
    return f"{time.strftime('%H:%M:%S')} {text}"


class JobLink:
    """Progress, logs, lease and cancel of one claimed job."""

    def __init__(self, store: JobStore, job: Job, owner: Owner, settings: WorkerSettings):
        self.store, self.job_id, self.owner, self.settings = store, job.id, owner, settings
        self.stop = threading.Event()
        self.lost = False
        """The lease went to someone else: stop and write nothing more."""
        self.cancelled = False
        self.shutdown = False
        """This worker is shutting down: stop, checkpoint, and give the job back."""
        self.yielding = False
        """Another tenant's turn (worker.fair): stop, checkpoint, and give the job back."""
        self._yield_after = yield_wait(2, settings.share_after_seconds,
                                       settings.time_slice_seconds)
        """The least time on this worker after which the job may be asked to give it up (a gap
        of two workers is one every rule of the fair share asks for)."""
        self._lock = threading.Lock()
        self._logs: list[str] = []
        self._pending: dict[str, Any] | None = None
        self._milestones: list[dict[str, Any]] = []
        """Progress states each written as an event of its own at the next heartbeat."""
        self._frame = job.frame
        self._fraction = job.fraction
        self._start = (time.monotonic(), job.fraction)
        self._cancel_seen: float | None = None
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"heartbeat-{job.id}",
                                        daemon=True)

    # -- called by the job's main thread ----------------------------------------------------------
    def start(self) -> JobLink:
        self._thread.start()
        return self

    def log(self, line: str) -> None:
        with self._lock:
            self._logs.append(log_line(line))

    def update(self, *, fraction: float, milestone: bool = False, **fields: Any) -> None:
        """New progress (stage, frame, frames, iteration, iterations, message): kept in memory,
        written by the next heartbeat. A `milestone`, and any update that changes the frame, is
        never merged with later updates: it becomes an event of its own (a client watching for
        frame 2 sees frame 2 even when it took less than a heartbeat). The fraction never goes
        back; the ETA extrapolates the rate of this run (a resumed job measures its own speed,
        not the lost worker's)."""
        now = time.monotonic()
        with self._lock:
            self._fraction = max(self._fraction, min(float(fraction), 1.0))
            t0, f0 = self._start
            done = self._fraction - f0
            eta = None
            if self._fraction >= 1.0:
                eta = 0.0
            elif done > 1e-3 and now - t0 > 2.0:  # a rate over less is noise
                eta = round((now - t0) / done * (1.0 - self._fraction), 1)
            self._pending = {**(self._pending or {}), **fields, "fraction": self._fraction,
                             "eta_s": eta}
            if milestone or fields.get("frame", self._frame) != self._frame:
                self._milestones.append(self._pending)
                self._pending = None
            self._frame = fields.get("frame", self._frame)

    def should_stop(self) -> bool:
        return self.stop.is_set()

    def close(self) -> None:
        """Flush what is pending and stop the heartbeat (call before finishing the job)."""
        self._done.set()
        if self._thread.is_alive():
            self._thread.join(timeout=30)
        self._flush()

    # -- the heartbeat thread ---------------------------------------------------------------------
    def _flush(self) -> tuple[bool, bool]:
        with self._lock:
            logs, self._logs = self._logs, []
            progress, self._pending = self._pending, None
            milestones, self._milestones = self._milestones, []
        if logs:
            self.store.append_logs(self.job_id, logs)
        if self.lost:
            return False, False
        return self.store.heartbeat(self.job_id, self.owner, self.settings.lease_seconds,
                                    progress, milestones=milestones)

    def _run(self) -> None:
        s = self.settings
        tick = min(s.watch_seconds, s.heartbeat_seconds)
        beat = time.monotonic() + s.heartbeat_seconds
        while not self._done.wait(tick):
            if time.monotonic() >= beat:  # write, renew the lease, see a cancel
                beat = time.monotonic() + s.heartbeat_seconds
                try:
                    owned, cancel = self._flush()
                except Exception as exc:  # the database is briefly away: keep the job running
                    self.log(f"heartbeat failed ({type(exc).__name__}: {exc}); retrying")
                    continue
                waiting = owned  # `_may_yield` looks for a waiting tenant itself
            else:  # between heartbeats: only look
                try:
                    cancel, waiting = self.store.watch(self.job_id, str(self.owner),
                                                       starting_seconds=s.stall_seconds)
                except Exception:  # the database is away: the next heartbeat says so
                    continue
                owned = not self.lost
            if not owned and not self.lost:
                self.lost = True
                self.stop.set()
            if cancel and not self.cancelled:
                self.cancelled = True
                self._cancel_seen = time.monotonic()
                self.log("cancel requested: stopping after the current step")
                self.stop.set()
            if (owned and waiting and not (self.cancelled or self.yielding)
                    and self._may_yield()):
                self.yielding = True
                self.log("another tenant waits with fewer jobs on the workers: stopping after "
                         "the current step, back in the queue (fair share)")
                self.stop.set()
            if (self._cancel_seen is not None and not self._done.is_set()
                    and time.monotonic() - self._cancel_seen > s.cancel_grace_seconds):
                self._kill_self()

    def _may_yield(self) -> bool:
        """Whether the fair share asks this job to give its worker up now (worker.fair)."""
        if self._yield_after is None or time.monotonic() - self._start[0] < self._yield_after:
            return False
        s = self.settings
        try:
            return self.store.ask_to_yield(self.job_id, str(self.owner),
                                           share_after=s.share_after_seconds,
                                           time_slice=s.time_slice_seconds,
                                           starting_seconds=s.stall_seconds)
        except Exception as exc:  # the database is briefly away: ask at the next beat
            self.log(f"fair share check failed ({type(exc).__name__}: {exc}); retrying")
            return False

    def _kill_self(self) -> None:
        """The job did not reach a step boundary in time: record the cancel and end this process
        (a prefork child; the worker starts a fresh one)."""
        self.log(f"job did not stop within {self.settings.cancel_grace_seconds:.0f} s of the "
                 "cancel; ending the worker process")
        try:
            self._flush()
            self.store.finish(self.job_id, self.owner, "cancelled", None,
                              "cancelled (worker process ended)")
        finally:
            os.kill(os.getpid(), signal.SIGKILL)
