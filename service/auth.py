"""Bearer API keys and tenants.

A key reads `dgs_<id>_<secret>`: the id is public (listings, logs), the secret is 256 random
bits of which only a SHA-256 is stored, compared in constant time. Keys travel only in the
`Authorization: Bearer` header, never in a URL (where proxies and browser history keep them).
Every key belongs to a tenant; everything a tenant creates is invisible to the others.

While no active key exists the service is a single-user tool: requests run as tenant "local"
without a key, and `dgs serve` refuses to listen beyond loopback (`check_bind`). Once a key
exists, every /v1 request needs a valid one.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import hmac
import ipaddress
import re
import secrets
import socket
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy import func, select, update

from service.deps import ServicesDep
from service.errors import ApiError
from worker.db import session_scope
from worker.models import ApiKey, Asset, Capture, Job, utcnow
from worker.settings import WorkerSettings

__all__ = [
    "LOCAL_TENANT",
    "BindRefused",
    "TenantDep",
    "check_bind",
    "create_key",
    "has_active_key",
    "list_keys",
    "revoke_key",
    "tenant_holdings",
    "tenant_of",
]

LOCAL_TENANT = "local"
_KEY = re.compile(r"^dgs_([0-9a-f]{16})_([A-Za-z0-9_\-]{20,128})$")
_TENANT = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")
LAST_USED_RESOLUTION = dt.timedelta(minutes=1)
"""last_used_at is written at most this often per key (not a database write per request)."""

bearer = HTTPBearer(auto_error=False, description="An API key: `Authorization: Bearer dgs_...`")


def _digest(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


def create_key(url: str, tenant: str, name: str = "") -> tuple[ApiKey, str]:
    """A new key for `tenant`: (its row, the key itself, which is shown only this once)."""
    if not _TENANT.match(tenant):
        raise ValueError(f"tenant: expected 1-64 letters, digits, '_', '.', '-', got {tenant!r}")
    if len(name) > 128:
        raise ValueError("name: at most 128 characters")
    key_id, secret = secrets.token_hex(8), secrets.token_urlsafe(32)
    with session_scope(url) as s:
        row = ApiKey(id=key_id, tenant=tenant, name=name, secret_sha256=_digest(secret))
        s.add(row)
    return row, f"dgs_{key_id}_{secret}"


def tenant_holdings(url: str, tenant: str) -> dict[str, int]:
    """How many captures, jobs and assets `tenant` has (those of "local" were made before any
    key existed and are reached only by a key of tenant "local")."""
    with session_scope(url, write=False) as s:
        return {table.__tablename__: s.scalar(select(func.count()).select_from(table)
                                              .where(table.tenant == tenant))
                for table in (Capture, Job, Asset)}


def list_keys(url: str) -> list[ApiKey]:
    with session_scope(url, write=False) as s:
        return list(s.scalars(select(ApiKey).order_by(ApiKey.created_at, ApiKey.id)))


def revoke_key(url: str, key_id: str) -> ApiKey | None:
    """Revoke a key (at once, for every process); None when there is no such key."""
    with session_scope(url) as s:
        row = s.get(ApiKey, key_id)
        if row is not None and row.revoked_at is None:
            row.revoked_at = utcnow()
        return row


def has_active_key(url: str) -> bool:
    with session_scope(url, write=False) as s:
        return s.scalar(select(ApiKey.id).where(ApiKey.revoked_at.is_(None)).limit(1)) is not None


def _verify(url: str, key: str) -> str:
    """The tenant of a valid key; ApiError 401 otherwise."""
    m = _KEY.match(key)
    if m is None:
        raise ApiError(401, "malformed API key; expected dgs_<id>_<secret>")
    key_id, secret = m.groups()
    with session_scope(url, write=False) as s:
        row = s.get(ApiKey, key_id)
    # Compare even for an unknown id, so timing does not tell which ids exist.
    stored = row.secret_sha256 if row is not None else "0" * 64
    if not hmac.compare_digest(stored, _digest(secret)) or row is None:
        raise ApiError(401, "invalid API key")
    if row.revoked_at is not None:
        raise ApiError(401, f"API key {key_id} was revoked; ask for a new one")
    now = utcnow()
    if row.last_used_at is None or now - row.last_used_at > LAST_USED_RESOLUTION:
        with session_scope(url) as s:
            s.execute(update(ApiKey).where(ApiKey.id == key_id).values(last_used_at=now))
    return row.tenant


def tenant_of(request: Request, services: ServicesDep,
              credentials: Annotated[HTTPAuthorizationCredentials | None,
                                     Depends(bearer)] = None) -> str:
    """The caller's tenant (a FastAPI dependency of every /v1 route)."""
    url = services.store.url
    if credentials is not None:
        return _verify(url, credentials.credentials.strip())
    if request.headers.get("authorization"):
        raise ApiError(401, "unsupported Authorization header; use 'Bearer <API key>'")
    if has_active_key(url):
        raise ApiError(401, "an API key is required: send 'Authorization: Bearer <key>' "
                            "(create one with `dgs keys create --tenant NAME`)")
    return LOCAL_TENANT


TenantDep = Annotated[str, Depends(tenant_of)]


class BindRefused(ValueError):
    """`dgs serve` was asked to listen beyond loopback while no API key exists."""


def is_loopback(host: str) -> bool:
    """True when `host` names only loopback addresses (127.0.0.0/8, ::1, localhost)."""
    name = host.strip().strip("[]")
    if name.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(name, None)
    except OSError:
        return False
    return bool(infos) and all(ipaddress.ip_address(str(i[4][0]).split('%')[0]).is_loopback for i in infos)


def check_bind(host: str, settings: WorkerSettings) -> None:
    """Refuse (BindRefused) to serve on a non-loopback `host` while no active key exists:
    anyone on the network could otherwise use the service as tenant "local"."""
    if is_loopback(host) or has_active_key(settings.database):
        return
    raise BindRefused(
        f"refusing to listen on {host!r}: no API key exists, so anyone who can reach this "
        "address could use the service. Create a key first (`dgs keys create --tenant NAME`) "
        "or listen on 127.0.0.1.")
