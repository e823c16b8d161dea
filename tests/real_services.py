"""Real PostgreSQL and Redis for the tests that need them (no mocks).

Each test session gets a database of its own (created, then dropped) and a Redis key prefix and
Celery queue of its own, so parallel runs on one machine do not see each other. Without the
services the tests skip with a message that says how to start them; with
DGS_REQUIRE_SERVICES=1 (CI) they fail instead.
"""

from __future__ import annotations

import os
import secrets
import socket
from collections.abc import Iterator
from urllib.parse import urlparse

import pytest

PG_URL = os.environ.get("DGS_TEST_POSTGRES", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres")
REDIS_URL = os.environ.get("DGS_TEST_REDIS", "redis://127.0.0.1:6379/0")

HOW = {
    "postgres": "start it with: pg_ctlcluster --skip-systemctl-redirect $(ls /etc/postgresql) main "
                "start (or set DGS_TEST_POSTGRES to a server URL)",
    "redis": "start it with: redis-server --daemonize yes --bind 127.0.0.1 --port 6379 (or set "
             "DGS_TEST_REDIS)",
}


def _reachable(url: str) -> bool:
    u = urlparse(url.replace("postgresql+psycopg", "postgresql"))
    try:
        with socket.create_connection((u.hostname or "127.0.0.1", u.port or 0), timeout=1.0):
            return True
    except OSError:
        return False


def require(service: str, url: str) -> None:
    """Skip (or, under DGS_REQUIRE_SERVICES=1, fail) when `service` at `url` is unreachable."""
    if _reachable(url):
        return
    message = f"{service} is not reachable at {url}; {HOW[service]}"
    if os.environ.get("DGS_REQUIRE_SERVICES") == "1":
        pytest.fail(f"DGS_REQUIRE_SERVICES=1 and {message}")
    pytest.skip(message)


def postgres_database() -> Iterator[str]:
    """A fresh PostgreSQL database for this session; dropped afterwards."""
    require("postgres", PG_URL)
    import sqlalchemy as sa

    name = f"dgs_test_{secrets.token_hex(4)}"
    admin = sa.create_engine(PG_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as c:
        c.exec_driver_sql(f'CREATE DATABASE "{name}"')
    base = PG_URL.rsplit("/", 1)[0]
    try:
        yield f"{base}/{name}"
    finally:
        from worker.db import engine_for

        url = f"{base}/{name}"
        engine_for(url).dispose()
        with admin.connect() as c:
            c.exec_driver_sql(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        admin.dispose()


def redis_namespace() -> Iterator[tuple[str, str]]:
    """(broker URL, key prefix) for this session; its keys are deleted afterwards."""
    require("redis", REDIS_URL)
    import redis

    prefix = f"dgs-test-{secrets.token_hex(4)}:"
    try:
        yield REDIS_URL, prefix
    finally:
        client = redis.Redis.from_url(REDIS_URL)
        keys = list(client.scan_iter(match=f"{prefix}*"))
        if keys:
            client.delete(*keys)
        client.close()
