"""Fixtures of the API tests: an app on a fresh data folder (SQLite job store and broker, local
artifact store; a few tests also on PostgreSQL), keys of two tenants, a small real capture
(core.synth) and helpers that speak tus."""

from __future__ import annotations

import socket
import threading
import warnings
from collections.abc import Callable
from pathlib import Path

import pytest
import uvicorn

# Starlette's TestClient now suggests httpx2; the dev extra installs httpx, which works.
warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
from fastapi.testclient import TestClient  # noqa: E402
from leak_scan import LeakScan  # noqa: E402
from service_harness import capture_files, make_settings, manifest_of, upload_file  # noqa: E402
from live_server import wait_for  # noqa: E402

from service.app import create_app
from service.auth import create_key
from service.settings import ServiceSettings


@pytest.fixture(scope="session", autouse=True)
def leak_scan(tmp_path_factory: pytest.TempPathFactory) -> LeakScan:
    """Every response of the session is scanned for the server's folders (leak_scan.py)."""
    with LeakScan(str(tmp_path_factory.getbasetemp())).installed() as scan:
        yield scan


@pytest.fixture(autouse=True)
def no_server_paths(leak_scan: LeakScan):
    """Fails a test whose responses showed a client a data or scratch folder."""
    before = len(leak_scan.leaks)
    yield
    leaks = leak_scan.leaks[before:]
    if leaks:
        pytest.fail("responses name server folders:\n" + "\n".join(
            f"  {x.method} {x.url} -> {x.status}: {x.text}" for x in leaks), pytrace=False)


@pytest.fixture(params=["sqlite"])
def database_url(request, tmp_path: Path) -> str | None:
    """None (SQLite in the data folder); tests parametrize it indirectly with "postgres"."""
    if request.param == "sqlite":
        return None
    return request.getfixturevalue("pg_empty")


@pytest.fixture
def settings(tmp_path: Path, database_url: str | None) -> ServiceSettings:
    return make_settings(tmp_path / "data", database_url=database_url)


@pytest.fixture
def app(settings: ServiceSettings):
    return create_app(settings)


@pytest.fixture
def client(app) -> TestClient:
    with TestClient(app) as c:
        yield c


@pytest.fixture
def services(app):
    return app.state.services


@pytest.fixture
def live_api(app):
    """(URL, services): `app` (the one `client` talks to) also served by a real uvicorn on a
    loopback port, for requests that must really run at the same time."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    wait_for(lambda: server.started or not thread.is_alive(), 30, "uvicorn to start")
    assert thread.is_alive(), "uvicorn stopped"
    yield f"http://127.0.0.1:{sock.getsockname()[1]}", app.state.services
    server.should_exit = True
    thread.join(timeout=10)
    sock.close()


@pytest.fixture
def tenants(settings: ServiceSettings) -> dict[str, dict[str, str]]:
    """Authorization headers of tenants "a" and "b" (so keys are required from here on)."""
    out = {}
    for tenant in ("a", "b"):
        _, key = create_key(settings.database, tenant, f"test {tenant}")
        out[tenant] = {"Authorization": f"Bearer {key}"}
    return out


@pytest.fixture(scope="session")
def synth_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real capture: one frame, 8 views of 32x32, masks and normal priors."""
    from core.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("service-capture") / "capture"
    synthesize(out, SynthConfig(frames=1, views=8, width=32, height=32, ao_directions=8))
    return out


@pytest.fixture
def new_capture(client: TestClient) -> Callable[..., dict]:
    """POST /v1/captures with the manifest of `files`; returns the capture."""

    def make(files: dict[str, bytes], headers: dict | None = None, fmt: str = "canonical",
             **extra) -> dict:
        r = client.post("/v1/captures", headers=headers or {},
                        json={"format": fmt, "manifest": manifest_of(files), **extra})
        assert r.status_code == 201, r.text
        return r.json()

    return make


@pytest.fixture
def ready_capture(client: TestClient, new_capture, synth_capture: Path):
    """Upload and commit the synthetic capture as a tenant; returns the capture id."""

    def make(headers: dict | None = None) -> str:
        files = capture_files(synth_capture)
        capture = new_capture(files, headers)
        for path, data in files.items():
            upload_file(client, capture["id"], path, data, headers)
        r = client.post(f"/v1/captures/{capture['id']}/commit", headers=headers or {})
        assert r.status_code == 200, r.text
        return capture["id"]

    return make
