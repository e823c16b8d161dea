"""Session fixtures shared by tests/worker and tests/service: the real PostgreSQL and Redis."""

from __future__ import annotations

import pytest

import real_services as services


@pytest.fixture(scope="session")
def pg_url():
    """URL of a fresh PostgreSQL database (dropped at the end of the session)."""
    yield from services.postgres_database()


@pytest.fixture(scope="session")
def redis_broker():
    """(Redis URL, key prefix) private to this session."""
    yield from services.redis_namespace()
