"""What one tenant may hold and how fast it may change things, kept in the job store so that
every API process sees the same numbers (docs/design.md 3.5, issue 42).

- **Active jobs**: a tenant's queued and running jobs (a job run as parts counts once) are
  counted in the transaction that would add one more, under a per-tenant lock, so concurrent
  submits cannot pass the cap together (`JobStore.active_jobs`, `hold_cap`).
- **Rate**: a token bucket per tenant and limit (`take`): `burst` tokens, refilled at `rate`
  a second, one taken per request. The row is read first without a lock, so a request over
  the limit costs a read and no write; only a request that may pass locks the row.

The clock is the caller's (seconds since the epoch: the API processes of a deployment share
wall time, not a monotonic clock); tests drive it.
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import text
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from worker.db import session_scope
from worker.models import RateBucket

__all__ = ["CapReached", "Rate", "lock_tenant", "peek", "take"]


class CapReached(Exception):
    """A tenant holds `active` queued or running jobs, `cap` or more: no other is queued."""

    def __init__(self, active: int, cap: int):
        super().__init__(f"{active} jobs queued or running; the cap is {cap}")
        self.active, self.cap = active, cap


@dataclass(frozen=True)
class Rate:
    """A token bucket: at most `burst` requests at once, `per_second` on average."""

    per_second: float
    burst: int

    def __post_init__(self):
        if not self.per_second > 0:
            raise ValueError(f"per_second: expected a positive rate, got {self.per_second}")
        if self.burst < 1:
            raise ValueError(f"burst: expected at least 1, got {self.burst}")

    def refill(self, tokens: float, stamp: float, now: float) -> float:
        """The tokens at `now` of a bucket that held `tokens` at `stamp` (a clock that went
        back, another host's, refills nothing)."""
        return min(float(self.burst), tokens + max(0.0, now - stamp) * self.per_second)

    def wait(self, tokens: float) -> float:
        """Seconds until a bucket holding `tokens` has one to give (0: it has)."""
        return 0.0 if tokens >= 1.0 else (1.0 - tokens) / self.per_second

    def take(self, tokens: float, stamp: float, now: float) -> tuple[float, float, float]:
        """One request at `now` on a bucket that held `tokens` at `stamp`: (seconds to wait, 0.0
        when a token was taken; the bucket's tokens and stamp after it)."""
        tokens = self.refill(tokens, stamp, now)
        if wait := self.wait(tokens):
            return wait, tokens, stamp
        return 0.0, tokens - 1.0, max(stamp, now)


def lock_tenant(s: Session, tenant: str) -> None:
    """Serialize the transactions that count and add a tenant's jobs. SQLite's write
    transactions already run one at a time (BEGIN IMMEDIATE, worker.db); PostgreSQL takes a
    transaction-scoped advisory lock on the tenant's name."""
    if s.get_bind().dialect.name == "postgresql":
        s.execute(text("SELECT pg_advisory_xact_lock(hashtext(:name))"),
                  {"name": f"dgs-active-jobs:{tenant}"})


def peek(url: str, key: str, rate: Rate, now: float) -> float:
    """The seconds until bucket `key` has a token (0.0: it has one now), taking none: one read,
    no lock."""
    with session_scope(url, write=False) as s:
        row = s.get(RateBucket, key)
        return 0.0 if row is None else rate.wait(rate.refill(row.tokens, row.stamp, now))


def take(url: str, key: str, rate: Rate, now: float) -> float:
    """Take a token from bucket `key` of the job store at `url`: 0.0 when taken, else the
    seconds until one will be there (nothing taken)."""
    if wait := peek(url, key, rate, now):
        return wait
    for _ in range(3):  # two processes adding a tenant's first row: the loser reads it
        try:
            with session_scope(url) as s:
                row = s.get(RateBucket, key, with_for_update=True)
                if row is None:
                    s.add(RateBucket(key=key, tokens=rate.burst - 1.0, stamp=now))
                    return 0.0
                wait, tokens, stamp = rate.take(row.tokens, row.stamp, now)
                if not wait:
                    row.tokens, row.stamp = tokens, stamp
                return wait
        except IntegrityError:
            continue
    raise RuntimeError(f"rate bucket {key}: could not be added")
