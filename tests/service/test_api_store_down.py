"""A job store that cannot be reached (PostgreSQL stopped, restarted, its network gone) is an
outage of the service, not a bug in the request: the API answers 503 with a JSON error and
Retry-After, and serves again as soon as the store is back (tests/deploy stops the deployment's
PostgreSQL container for real)."""

from __future__ import annotations

import socket

import pytest


CAPTURE = {"name": "c", "format": "canonical", "manifest": {"files": [
    {"path": "capture.json", "size": 10, "sha256": "0" * 64}]}}
"""A valid request body: only the job store stands between it and an answer."""


@pytest.fixture
def closed_port() -> int:
    """A loopback port nothing listens on: connecting there is refused at once."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("method, path", [
    ("GET", "/v1/jobs"), ("GET", "/v1/info"), ("POST", "/v1/captures"),
    ("GET", "/v1/jobs/job_missing/events")])
def test_an_unreachable_job_store_answers_503_then_recovers(client, services, closed_port,
                                                            method, path):
    url = services.store.url
    assert client.get("/v1/jobs").status_code == 200
    # A real PostgreSQL URL where no server answers, as when its container is stopped.
    services.store.url = f"postgresql+psycopg://dgs:x@127.0.0.1:{closed_port}/dgs"
    try:
        r = client.request(method, path, json=CAPTURE if method == "POST" else None)
        assert r.status_code == 503, r.text
        error = r.json()["error"]
        assert error["code"] == "unavailable" and error["retryable"] is True
        assert "job store is unreachable" in error["message"]
        assert str(closed_port) not in r.text  # nothing of the server's set-up is shown
        assert int(r.headers["Retry-After"]) > 0
        assert client.get("/readyz").status_code == 503
    finally:
        services.store.url = url
    assert client.get("/v1/jobs").status_code == 200
    assert client.get("/readyz").status_code == 200
