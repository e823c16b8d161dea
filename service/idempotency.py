"""`Idempotency-Key` on the submits (POST /v1/jobs, /v1/renders, /v1/exports; docs/design.md
3.5), as payment and cloud APIs have it: a client that sends a submit again after a timeout
(every HTTP client with retries) with the same key gets the job the first one made, not a
second job.

Per tenant. A stored key answers its first job (202, `Idempotent-Replayed: true`) whatever
that job has become; the same key with another request (another operation, another body once
validated) is refused with 422; keys expire (`DGS_IDEMPOTENCY_KEY_HOURS`) and go with their
job. Two submits racing with one key make one job: the key is inserted in the transaction that
adds the job, under a unique constraint (`worker.idempotency`), and the loser answers the
winner's job."""

from __future__ import annotations

import datetime as dt
import hashlib
import json
from typing import Annotated

from fastapi import Header
from pydantic import BaseModel

from service.deps import Services
from service.errors import ApiError
from worker.idempotency import Idempotency, recall
from worker.models import Job, utcnow

__all__ = ["IdempotencyKey", "KEY_PATTERN", "Submit"]

KEY_PATTERN = r"^[!-~]{1,255}$"
IdempotencyKey = Annotated[str | None, Header(
    alias="Idempotency-Key", pattern=KEY_PATTERN, description=(
        "A key of your own (1-255 visible ASCII characters; a UUID is usual) that makes the "
        "submit safe to send again: while it lives (24 h by default), the same key answers "
        "the job the first submit made (202, header Idempotent-Replayed: true) instead of "
        "making another; the same key with another request is refused with 422."))]


class Submit:
    """One submit's `Idempotency-Key` (None: no key): the job a stored key made, or what to
    keep with the job this submit makes."""

    def __init__(self, services: Services, tenant: str, key: str | None, operation: str,
                 body: BaseModel):
        self.services, self.tenant, self.key = services, tenant, key
        text = json.dumps({"operation": operation, "body": body.model_dump(mode="json")},
                          sort_keys=True, separators=(",", ":"))
        self.digest = hashlib.sha256(text.encode()).hexdigest()

    @property
    def idempotency(self) -> Idempotency | None:
        """What the job store keeps with the new job (None without a key)."""
        if self.key is None:
            return None
        hours = self.services.settings.idempotency_key_hours
        return Idempotency(self.tenant, self.key, self.digest,
                           utcnow() + dt.timedelta(hours=hours))

    def first(self) -> Job | None:
        """The job this key already made (None: none, or no key); 422 when the key was used
        for another request."""
        if self.key is None:
            return None
        with self.services.store.session(write=False) as s:
            row = recall(s, self.tenant, self.key)
            job = s.get(Job, row.job_id) if row is not None else None
        if row is None or job is None:
            return None
        if row.request_sha256 != self.digest:
            message = ("was used for another request (another operation or body); use a new "
                       "key for a new request")
            raise ApiError(422, f"Idempotency-Key: {message}", code="idempotency_key_reused",
                           details=[{"path": "header.Idempotency-Key", "message": message}])
        return job
