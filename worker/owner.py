"""Who holds a job's lease: host, process id and its start time, and a random token; and
whether such a holder is gone (a lease of a dead process on this machine is taken over at once
instead of waiting for it to expire)."""

from __future__ import annotations

import os
import secrets
import socket
from dataclasses import dataclass

__all__ = ["Owner"]


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
