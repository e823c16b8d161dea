"""Who holds a job's lease: host, process id and its start time, and a random token; and
whether such a holder is gone (a lease of a dead process on this machine is taken over at once
instead of waiting for it to expire). Also who ran a job: the lease is gone once it ends, so
each claim is kept on the row (`Job.worker`, `Job.runs`: docs/design.md 4.4)."""

from __future__ import annotations

import datetime as dt
import os
import secrets
import socket
from dataclasses import dataclass
from typing import Any

__all__ = ["MAX_RUNS", "Owner", "lease_prefix", "run_ended", "run_started"]

MAX_RUNS = 20
"""Runs (claims) a job row keeps, the newest."""


def _process_start(pid: int) -> str | None:
    """The kernel's start time of `pid` (clock ticks since boot), to tell a dead process from a
    new one that reused its pid; None where /proc does not exist."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read().decode(errors="replace")
        return stat.rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


@dataclass(frozen=True)
class Owner:
    """Who holds a lease: host, process id and its start time, and a random token."""

    host: str
    pid: int
    started: str
    token: str

    @classmethod
    def current(cls) -> Owner:
        pid = os.getpid()
        return cls(socket.gethostname(), pid, _process_start(pid) or "?", secrets.token_hex(4))

    def __str__(self) -> str:
        return f"{self.host}/{self.pid}/{self.started}/{self.token}"

    @property
    def worker(self) -> str:
        """host/pid: the worker process as the API shows it."""
        return f"{self.host}/{self.pid}"

    @classmethod
    def parse(cls, text: str) -> Owner | None:
        parts = text.split("/")
        if len(parts) != 4 or not parts[1].isdigit():
            return None
        return cls(parts[0], int(parts[1]), parts[2], parts[3])

    def is_dead_here(self) -> bool:
        """True when this owner ran on this machine and its process is gone (a lease it holds can
        be taken over at once instead of waiting for it to expire)."""
        if self.host != socket.gethostname() or self.started == "?":
            return False
        return _process_start(self.pid) != self.started


def lease_prefix(pid: int) -> str | None:
    """How every lease owner of process `pid` of this machine begins (host/pid/start/), or None
    when that process is gone."""
    started = _process_start(pid)
    if started is None and os.path.isdir("/proc"):
        return None
    return f"{socket.gethostname()}/{pid}/{started or '?'}/"


def _ended(run: dict[str, Any], outcome: str, now: dt.datetime) -> dict[str, Any]:
    return {**run, "ended_at": now.isoformat(), "outcome": outcome}


def run_started(job: Any, owner: Owner, now: dt.datetime) -> None:
    """`job` (a worker.models.Job row) was claimed by `owner`: it is its worker from now on,
    also after it ends, and a run is added to its history (the run before, if it never ended,
    was lost with its worker)."""
    runs = list(job.runs or [])
    if runs and "ended_at" not in runs[-1]:
        runs[-1] = _ended(runs[-1], "lost", now)
    runs.append({"attempt": job.attempts, "worker": owner.worker,
                 "started_at": now.isoformat()})
    job.worker, job.runs = owner.worker, runs[-MAX_RUNS:]


def run_ended(job: Any, outcome: str, now: dt.datetime) -> None:
    """`job`'s current run ended with `outcome` (succeeded, failed, cancelled, released)."""
    runs = list(job.runs or [])
    if runs and "ended_at" not in runs[-1]:
        runs[-1] = _ended(runs[-1], outcome, now)
        job.runs = runs
