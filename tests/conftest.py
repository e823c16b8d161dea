"""Session fixtures shared by tests/worker and tests/service: the real PostgreSQL and Redis;
and the device training's `auto` picks in every test (the CPU)."""

from __future__ import annotations

import os

import pytest

# `make test` runs the suite in pytest-xdist processes (one a core): each keeps to its share of
# the cores, so that two processes' OpenMP threads do not fight over them (set before anything
# loads torch; a value the user set is kept).
if os.environ.get("PYTEST_XDIST_WORKER"):
    _share = (os.cpu_count() or 1) // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, _share)))

import core  # noqa: E402,F401  (before any test module loads torch: OpenMP's passive wait)
import real_services as services

# Training's device `auto` means the CPU in the tests, also in the processes they start (workers,
# CLI runs): STYLE 12, and the exact-resume checks hold on the CPU only (CUDA's atomic gradient
# sums are not bit-reproducible). GPU tests name `cuda`; DGS_DEVICE=cuda runs the rest there too.
os.environ.setdefault("DGS_DEVICE", "cpu")


@pytest.fixture(scope="session")
def pg_url():
    """URL of a fresh PostgreSQL database (dropped at the end of the session)."""
    yield from services.postgres_database()


@pytest.fixture(scope="session")
def redis_broker():
    """(Redis URL, key prefix) private to this session."""
    yield from services.redis_namespace()
