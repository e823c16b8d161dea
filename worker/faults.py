"""A fault the tests inject into a pool process: the hang of issue 42, on purpose.

`DGS_FAULT_HANG=<where>:<marker path>` in a worker's environment makes the first pool process
that reaches `where` (`start`: its task began, before the claim; `claimed`: it holds its job's
lease) create the marker file and deadlock on a mutex it already holds, keeping the GIL, as the
pool process that hung in gc did: no Python code of that process runs again, its heartbeat
included, and only the default action of a signal (or SIGKILL) ends it. Never set in service.
"""

from __future__ import annotations

import ctypes
import os

__all__ = ["hang_if_asked"]


def hang_if_asked(where: str) -> None:
    """Hang forever here when DGS_FAULT_HANG asks for `where` and no process has yet."""
    asked = os.environ.get("DGS_FAULT_HANG", "")
    point, _, marker = asked.partition(":")
    if point != where or not marker:
        return
    try:
        os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:  # another process hung already: this one runs
        return
    libc = ctypes.PyDLL(None)  # PyDLL: the GIL stays held during the call
    mutex = ctypes.create_string_buffer(64)  # zeroed: a default (non-recursive) pthread mutex
    libc.pthread_mutex_lock(mutex)
    libc.pthread_mutex_lock(mutex)
