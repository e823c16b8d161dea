"""What the service benchmarks share: wait for a condition with a deadline."""

from __future__ import annotations

import time


def wait_until(condition, timeout: float, what: str, every: float = 0.2):
    """Poll `condition` every `every` seconds until it returns something truthy, and return
    that; TimeoutError naming `what` after `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := condition():
            return value
        time.sleep(every)
    raise TimeoutError(f"{what}: not within {timeout:.0f} s")
