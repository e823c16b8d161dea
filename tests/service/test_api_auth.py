"""Bearer keys (hashed, revocable, never in a URL), tenants that cannot see each other's
anything, the loopback-only rule without keys, and `dgs keys`."""

from __future__ import annotations

import hashlib

import pytest
from service_harness import TUS, tus_create, tus_patch
from sqlalchemy import select

from core.cli import main
from service.auth import BindRefused, check_bind, create_key, revoke_key
from worker.models import ApiKey


def test_without_keys_requests_run_as_local(client):
    r = client.get("/v1/info")
    assert r.status_code == 200 and r.json()["tenant"] == "local"
    assert r.json()["keys_required"] is False


def test_keys_are_required_once_one_exists(client, settings, tenants):
    assert client.get("/v1/info", headers=tenants["a"]).json()["tenant"] == "a"
    r = client.get("/v1/info")
    assert r.status_code == 401 and r.headers["WWW-Authenticate"].startswith("Bearer")
    assert r.json()["error"]["code"] == "unauthorized"
    token = tenants["a"]["Authorization"].split()[1]
    for headers in ({"Authorization": "Bearer nonsense"},
                    {"Authorization": f"Bearer {token[:-2]}xx"},
                    {"Authorization": f"Basic {token}"},
                    {"Authorization": f"Bearer dgs_{'0' * 16}_{'a' * 43}"}):
        assert client.get("/v1/info", headers=headers).status_code == 401, headers
    for name in ("api_key", "access_token", "token"):  # never taken from a URL
        r = client.get(f"/v1/info?{name}={token}")
        assert r.status_code == 400 and "unknown query parameter" in r.json()["error"]["message"]
    for open_path in ("/healthz", "/readyz"):
        assert client.get(open_path).status_code == 200
    assert client.options("/v1/uploads").status_code == 204


def test_revoked_keys_get_401(client, settings, tenants):
    key_id = tenants["b"]["Authorization"].split("_")[1]
    assert client.get("/v1/info", headers=tenants["b"]).status_code == 200
    assert revoke_key(settings.database, key_id).revoked_at is not None
    r = client.get("/v1/info", headers=tenants["b"])
    assert r.status_code == 401 and "revoked" in r.json()["error"]["message"]
    assert client.get("/v1/info", headers=tenants["a"]).status_code == 200


def test_only_a_hash_of_the_secret_is_stored(client, services, tenants):
    token = tenants["a"]["Authorization"].split()[1]
    key_id, secret = token[4:20], token[21:]
    client.get("/v1/info", headers=tenants["a"])
    with services.store.session(write=False) as s:
        row = s.scalar(select(ApiKey).where(ApiKey.id == key_id))
    assert row.secret_sha256 == hashlib.sha256(secret.encode()).hexdigest()
    assert secret not in repr(row.__dict__) and row.last_used_at is not None


@pytest.mark.parametrize("database_url", ["sqlite", "postgres"], indirect=True)
def test_tenants_cannot_see_each_others_anything(client, services, tenants, ready_capture,
                                                 new_capture, tmp_path):
    a, b = tenants["a"], tenants["b"]
    ready = ready_capture(a)
    uploading = new_capture({"capture.json": b"{}"}, a)["id"]
    upload = tus_create(client, uploading, "capture.json", 2, a).headers["Location"]
    job = client.post("/v1/jobs", json={"capture_id": ready, "params": {"preset": "test"}},
                      headers=a).json()["id"]
    src = tmp_path / "m.json"
    src.write_text("{}")
    services.blobs.put_file(f"jobs/{job}/artifacts/metrics.json", src)
    services.store.add_artifact(job, "metrics.json", kind="metrics", size=2,
                                sha256=hashlib.sha256(b"{}").hexdigest(),
                                content_type="application/json")
    from test_api_assets import exr_bytes

    asset = client.post("/v1/assets?filename=e.exr", content=exr_bytes(tmp_path),
                        headers=a).json()["id"]
    checks = [
        ("GET", f"/v1/captures/{ready}", {}), ("GET", f"/v1/captures/{ready}/files", {}),
        ("POST", f"/v1/captures/{uploading}/commit", {}),
        ("PATCH", f"/v1/captures/{uploading}/manifest", {"json": {"remove": ["capture.json"]}}),
        ("DELETE", f"/v1/captures/{ready}", {}),
        ("POST", "/v1/jobs", {"json": {"capture_id": ready}}),
        ("GET", f"/v1/jobs/{job}", {}), ("GET", f"/v1/jobs/{job}/events", {}),
        ("GET", f"/v1/jobs/{job}/logs", {}), ("POST", f"/v1/jobs/{job}/cancel", {}),
        ("POST", f"/v1/jobs/{job}/retry", {}), ("DELETE", f"/v1/jobs/{job}", {}),
        ("GET", f"/v1/jobs/{job}/artifacts", {}), ("GET", f"/v1/jobs/{job}/artifacts.zip", {}),
        ("GET", f"/v1/jobs/{job}/artifacts/metrics.json", {}),
        ("GET", f"/v1/assets/{asset}", {}), ("GET", f"/v1/assets/{asset}/content", {}),
        ("DELETE", f"/v1/assets/{asset}", {}),
        ("POST", "/v1/renders", {"json": {"job_id": job, "envmap": asset}}),
        ("POST", "/v1/renders", {"json": {"job_id": "x", "envmap": asset}}),
        ("HEAD", upload, {"headers": TUS}), ("DELETE", upload, {"headers": TUS}),
    ]
    for method, url, kwargs in checks:
        headers = {**kwargs.pop("headers", {}), **b}
        r = client.request(method, url, headers=headers, **kwargs)
        assert r.status_code == 404, (method, url, r.status_code, r.text)
    assert tus_patch(client, upload, 0, b"{}", b).status_code == 404
    assert tus_create(client, uploading, "capture.json", 2, b).status_code == 404
    for listing in ("/v1/captures", "/v1/jobs", "/v1/assets"):
        assert client.get(listing, headers=b).json()["items"] == []
    assert sum(client.get("/v1/info", headers=b).json()["jobs"].values()) == 0
    # tenant a still has everything, untouched
    assert client.get(f"/v1/captures/{ready}", headers=a).json()["state"] == "ready"
    assert client.get(f"/v1/jobs/{job}", headers=a).json()["state"] == "queued"
    assert client.get(f"/v1/assets/{asset}", headers=a).status_code == 200
    assert client.head(upload, headers={**TUS, **a}).status_code == 200
    assert len(client.get("/v1/captures", headers=a).json()["items"]) == 2


@pytest.mark.parametrize("host", ["127.0.0.1", "::1", "localhost", "127.0.0.2", "[::1]"])
def test_loopback_binds_without_keys(settings, host):
    check_bind(host, settings)


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.168.1.20", "10.0.0.1"])
def test_other_binds_need_a_key(settings, host):
    from worker.db import migrate

    migrate(settings.database)
    with pytest.raises(BindRefused, match="dgs keys create"):
        check_bind(host, settings)
    create_key(settings.database, "studio")
    check_bind(host, settings)


def test_serve_refuses_to_bind_beyond_loopback_without_keys(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("DGS_DATA_DIR", str(tmp_path / "data"))
    for name in ("DGS_DATABASE_URL", "DGS_BROKER_URL", "DGS_STORAGE_URL"):
        monkeypatch.delenv(name, raising=False)
    assert main(["serve", "--host", "0.0.0.0", "--port", "0", "--no-worker"]) == 2
    assert "refusing to listen on '0.0.0.0'" in capsys.readouterr().err


def test_keys_command(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("DGS_DATA_DIR", str(tmp_path / "data"))
    for name in ("DGS_DATABASE_URL", "DGS_BROKER_URL", "DGS_STORAGE_URL"):
        monkeypatch.delenv(name, raising=False)
    assert main(["keys", "create", "--tenant", "studio-1", "--name", "render farm"]) == 0
    key = capsys.readouterr().out.strip().splitlines()[-1]
    assert key.startswith("dgs_")
    assert main(["keys", "list"]) == 0
    listing = capsys.readouterr().out
    key_id = key.split("_")[1]
    assert key_id in listing and "studio-1" in listing and "render farm" in listing
    assert key.split("_", 2)[2] not in listing
    assert main(["keys", "revoke", key_id]) == 0
    assert main(["keys", "revoke", "0123456789abcdef"]) == 1
    assert main(["keys", "create", "--tenant", "bad tenant!"]) == 2
    capsys.readouterr()
    assert main(["keys", "list"]) == 0
    row = [line for line in capsys.readouterr().out.splitlines() if key_id in line][0]
    assert row.rstrip().endswith("Z")  # the revoked column holds a time



def test_a_new_key_notes_the_data_of_tenant_local(tmp_path, capsys, monkeypatch):
    """Data made before any key existed belongs to tenant "local": a key of another tenant
    does not reach it, and `dgs keys create` says so (a key of tenant local does)."""
    monkeypatch.setenv("DGS_DATA_DIR", str(tmp_path / "data"))
    for name in ("DGS_DATABASE_URL", "DGS_BROKER_URL", "DGS_STORAGE_URL"):
        monkeypatch.delenv(name, raising=False)
    assert main(["keys", "create", "--tenant", "first"]) == 0
    assert "note" not in capsys.readouterr().err  # nothing of tenant local yet
    from worker.models import Capture
    from worker.settings import WorkerSettings
    from worker.store import JobStore

    store = JobStore(WorkerSettings().database)
    with store.session() as s:
        s.add(Capture(id="cap_old", tenant="local", format="canonical", state="ready"))
    store.create("local", "reconstruct", {}, capture_id="cap_old")
    assert main(["keys", "create", "--tenant", "studio"]) == 0
    out = capsys.readouterr()
    assert "1 capture(s), 1 job(s) were made before any key existed (tenant 'local')" in out.err
    assert "--tenant local" in out.err and out.out.strip().splitlines()[-1].startswith("dgs_")
    assert main(["keys", "create", "--tenant", "local"]) == 0
    assert "note" not in capsys.readouterr().err
