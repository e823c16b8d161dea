"""A daemon thread that runs one pass of some work every `interval` seconds until stopped: the
sweeper's and the watchdog's loop. A pass that raises is logged and tried again at the next (the
job store may be briefly away)."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

__all__ = ["Periodic"]


class Periodic:
    """`start()` runs `work()` every `interval` seconds in a daemon thread called `name`, the
    first pass at once when `at_once`, else after one interval; `stop()` ends it."""

    def __init__(self, work: Callable[[], object], interval: float, *, name: str,
                 log: logging.Logger, what: str, at_once: bool = False):
        self.work, self.interval, self.name = work, interval, name
        self.log, self.what, self.at_once = log, what, at_once
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)

    def _loop(self) -> None:
        if not self.at_once and self._stop.wait(self.interval):
            return
        while True:
            try:
                self.work()
            except Exception:
                self.log.exception("%s failed; retrying in %.0f s", self.what, self.interval)
            if self._stop.wait(self.interval):
                return
