"""The watchdog of a worker's pool: a thread of the Celery parent that ends a pool process which
stopped making progress, so its slot frees and its job runs again within minutes instead of
waiting for the task's hard time limit (48 h and more).

A busy pool process shows progress through the job store: it claims its job's lease soon after
it takes the task, and renews it every heartbeat while the job runs. So a busy process is
silent when

- it holds a lease that has lapsed (no heartbeat for `lease_seconds`: the whole process is
  stuck, as a deadlock holding the GIL leaves it), or
- it has held no live lease for `stall_seconds` (stuck before its claim, say in an import, or
  after its job ended).

The watchdog kills a silent process (SIGKILL: a stuck one answers nothing else). Celery then
sees its pool process lost and puts the message back in the queue (acks late, reject on a lost
worker); the next pool process claims the job (a lease of a dead process on this machine is
taken over at once, worker.lease) and resumes it from its checkpoint. Only a lease holder may
write, so the killed attempt records nothing and the job succeeds once.
"""

from __future__ import annotations

import logging
import os
import signal
import time
from collections.abc import Callable

from worker.lease import lease_prefix
from worker.periodic import Periodic
from worker.settings import WorkerSettings
from worker.store import JobStore

__all__ = ["Watchdog"]

log = logging.getLogger("dgs.watchdog")
Busy = Callable[[], "dict[int, str]"]


class Watchdog:
    """`check()` once, or `start()` a daemon thread that checks every `interval` seconds.

    `busy()` answers the pool processes that run a task now, {pid: the task's job id} (in a
    Celery worker: its active requests); `kill(pid)` ends one (default SIGKILL)."""

    def __init__(self, settings: WorkerSettings, busy: Busy, *, store: JobStore | None = None,
                 kill: Callable[[int], None] | None = None, interval: float | None = None):
        self.settings, self.busy = settings, busy
        self.store = store or JobStore(settings.database)
        self.kill = kill or (lambda pid: os.kill(pid, signal.SIGKILL))
        self.interval = interval if interval is not None else max(
            min(settings.lease_seconds, settings.stall_seconds) / 4, 0.5)
        self._progress: dict[int, float] = {}
        """When (time.monotonic) each busy process last held a live lease, or was first seen."""
        self._periodic = Periodic(self.check, self.interval, name="dgs-watchdog", log=log,
                                  what="watchdog check")

    def check(self) -> dict[int, str]:
        """One look at every busy pool process; returns {pid: why} of those killed."""
        busy = self.busy()
        for pid in set(self._progress) - set(busy):
            del self._progress[pid]
        killed = {}
        for pid, job_id in busy.items():
            why = self._silent(pid, job_id)
            if why is None:
                continue
            log.warning("pool process %d (job %s) %s: killed; its job goes back to the queue "
                        "and resumes from its checkpoint", pid, job_id, why)
            try:
                self.kill(pid)
            except ProcessLookupError:
                pass
            self._progress.pop(pid, None)
            killed[pid] = why
        return killed

    def _silent(self, pid: int, job_id: str) -> str | None:
        """Why the busy process `pid` counts as silent, or None while it makes progress."""
        now = time.monotonic()
        first = self._progress.setdefault(pid, now)
        prefix = lease_prefix(pid)
        if prefix is None:  # it has just exited: nothing to do
            return None
        leases = self.store.leases_of(prefix)
        left = max((seconds for _, seconds in leases), default=None)
        if left is not None and left > 0:
            self._progress[pid] = now
            return None
        if left is not None:
            held = ", ".join(job for job, _ in leases)
            return (f"stopped renewing the lease of {held} (lapsed {-left:.0f} s ago; "
                    f"lease {self.settings.lease_seconds:.0f} s)")
        if now - first > self.settings.stall_seconds:
            return (f"has held no live lease for {now - first:.0f} s (stall limit "
                    f"{self.settings.stall_seconds:.0f} s)")
        return None

    def start(self) -> Watchdog:
        self._periodic.start()
        return self

    def stop(self) -> None:
        self._periodic.stop()
