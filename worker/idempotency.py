"""Idempotent submits in the job store (docs/design.md 3.5): a client's Idempotency-Key is kept
with the job its submit made, per tenant, until it expires, so a submit sent again (a retry
after a timeout) gets the first job instead of making a second.

The key is written in the same transaction as its job (`remember`, called by the job store's
create methods), under a unique constraint on (tenant, key): of two submits racing with one
key, the second insert fails with an IntegrityError, its whole transaction (its job too) is
rolled back, and `recall` then finds the first. Nothing checks first and inserts later."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from worker.models import IdempotencyKey, utcnow

__all__ = ["Idempotency", "forget_expired", "recall", "remember"]


@dataclass(frozen=True)
class Idempotency:
    """A key to keep with the job a submit makes."""

    tenant: str
    key: str
    request_sha256: str
    """What was asked: the operation and its validated body."""
    expires_at: dt.datetime


def remember(s: Session, idempotency: Idempotency | None, job_id: str) -> None:
    """Keep `idempotency` with the new job `job_id`, in its transaction (`s`). An expired row
    of the same key is replaced; a live one raises IntegrityError (on flush or commit), which
    rolls the job back with it."""
    if idempotency is None:
        return
    now = utcnow()
    s.execute(delete(IdempotencyKey).where(
        IdempotencyKey.tenant == idempotency.tenant, IdempotencyKey.key == idempotency.key,
        IdempotencyKey.expires_at <= now).execution_options(synchronize_session=False))
    s.add(IdempotencyKey(tenant=idempotency.tenant, key=idempotency.key,
                         request_sha256=idempotency.request_sha256, job_id=job_id,
                         created_at=now, expires_at=idempotency.expires_at))
    s.flush()


def recall(s: Session, tenant: str, key: str) -> IdempotencyKey | None:
    """The live (unexpired) row of `tenant`'s `key`, if any."""
    return s.scalar(select(IdempotencyKey).where(
        IdempotencyKey.tenant == tenant, IdempotencyKey.key == key,
        IdempotencyKey.expires_at > utcnow()))


def forget_expired(s: Session) -> int:
    """Delete the expired keys (the sweeper's pass); how many."""
    result = s.execute(delete(IdempotencyKey).where(IdempotencyKey.expires_at <= utcnow())
                       .execution_options(synchronize_session=False))
    return result.rowcount or 0
