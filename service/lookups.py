"""Tenant-scoped lookups: every object a request names is fetched here, filtered by the caller's
tenant, and answers 404 (never 403) when it belongs to another, so ids cannot be probed; and the
answer to a deletion the job store made or refused."""

from __future__ import annotations

from typing import TypeVar

from service.errors import ApiError
from worker.api_queries import Deleted
from worker.models import Asset, Capture, Job, Upload
from worker.store import JobStore

__all__ = ["deleted", "get_asset", "get_capture", "get_job", "get_upload", "missing"]

T = TypeVar("T")


def missing(kind: str, ident: str) -> ApiError:
    return ApiError(404, f"no {kind} {ident!r}", code="not_found")


def deleted(done: Deleted, kind: str, ident: str) -> list[str]:
    """What a deletion in the job store deleted (`Deleted.ids`); 404 when there was nothing
    of the tenant's to delete, 409 saying why it was refused."""
    if done.status == "missing":
        raise missing(kind, ident)
    if done.status == "refused":
        raise ApiError(409, done.why, retryable=done.retryable)
    return done.ids


def _found(row: T | None, visible: bool, kind: str, ident: str) -> T:
    """`row` when the store found it and it is `visible` to the caller; else 404."""
    if row is None or not visible:
        raise missing(kind, ident)
    return row


def get_capture(store: JobStore, capture_id: str, tenant: str) -> Capture:
    """The capture (its manifest not loaded: see staging.ManifestCache)."""
    return _found(store.capture(capture_id, tenant), True, "capture", capture_id)


def get_job(store: JobStore, job_id: str, tenant: str) -> Job:
    job = store.get(job_id, tenant)  # a part is reached through its job
    return _found(job, job is not None and job.parent_id is None, "job", job_id)


def get_upload(store: JobStore, upload_id: str, tenant: str) -> Upload:
    row = store.upload(upload_id, tenant)
    return _found(row, row is not None and row.state != "terminated", "upload", upload_id)


def get_asset(store: JobStore, asset_id: str, tenant: str) -> Asset:
    return _found(store.asset(asset_id, tenant), True, "asset", asset_id)
