"""What every request handler reaches through `Depends`: the process's services (settings, job
store, artifact store, Celery client, upload staging) held on app.state, and URL helpers."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Annotated, Any

from celery import Celery
from fastapi import Depends, Request

from service.errors import ApiError
from service.limits import Limits
from service.settings import ServiceSettings
from service.upload.staging import ManifestCache, Staging
from service.upload.tus import HashCache
from worker.blobs import BlobStore
from worker.models import utcnow
from worker.store import JobStore

__all__ = ["Services", "ServicesDep", "default_expiry", "get_services", "location"]


@dataclass
class Services:
    settings: ServiceSettings
    store: JobStore
    blobs: BlobStore
    celery: Celery
    staging: Staging
    manifests: ManifestCache
    hashes: HashCache
    """SHA-256 state of uploads in progress (service.upload.tus)."""
    limits: Limits
    """What one tenant may do at once (service.limits): 429s."""
    committer: Any = None
    """service.upload.commit.Committer: this process's background commits."""


async def get_services(request: Request) -> Services:
    # async: FastAPI would run a plain function in a worker thread, a hop on every request
    return request.app.state.services


ServicesDep = Annotated[Services, Depends(get_services)]


def location(services: Services, path: str) -> str:
    """`path` (starting with /) as clients should follow it (Location, `url` fields): under
    public_url when configured, else the path itself, a relative reference resolved against
    the URL the client used. Never built from the request's Host header, which a client (or
    whoever forwarded the request) chooses."""
    base = services.settings.public_url
    return base.rstrip("/") + path if base else path


def default_expiry(services: Services, given: dt.datetime | None) -> dt.datetime | None:
    """The expiry of a new object: the client's, else now + retention_days (None: kept)."""
    if given is not None:
        if given <= utcnow():
            raise ApiError(422, f"expires_at: {given.isoformat()} is in the past",
                           details=[{"path": "expires_at", "message": "must be in the future"}])
        return given.astimezone(dt.UTC)
    days = services.settings.retention_days
    return None if days is None else utcnow() + dt.timedelta(days=days)
