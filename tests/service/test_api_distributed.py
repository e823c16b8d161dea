"""The same app on the deployment stack (docs/design.md section 4): PostgreSQL job store, Redis
broker, S3-compatible artifact store (moto's server over HTTP). A committed capture is frozen
into the bucket, a job's message lands in Redis, artifacts stream back from S3 with Range."""

from __future__ import annotations

import hashlib
import secrets

import pytest
from fastapi.testclient import TestClient
from service_harness import capture_files, make_settings, upload_file

from service.app import create_app


@pytest.fixture(scope="module")
def s3_endpoint():
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0)
    server.start()
    host, port = server.get_host_and_port()
    yield f"http://{host}:{port}"
    server.stop()


@pytest.mark.parametrize("database_url", ["postgres"], indirect=True)
def test_the_distributed_stack(tmp_path, database_url, redis_broker, s3_endpoint, monkeypatch,
                               synth_capture):
    import boto3
    import redis

    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "test")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "test")
    bucket, (redis_url, prefix) = f"dgs-{secrets.token_hex(4)}", redis_broker
    boto3.client("s3", endpoint_url=s3_endpoint, region_name="us-east-1").create_bucket(
        Bucket=bucket)
    settings = make_settings(tmp_path / "data", database_url=database_url,
                             broker_url=redis_url, redis_key_prefix=prefix,
                             queue=f"q-{secrets.token_hex(4)}",
                             storage_url=f"s3://{bucket}/dgs", s3_endpoint_url=s3_endpoint,
                             s3_region="us-east-1")
    client = TestClient(create_app(settings))
    services = client.app.state.services
    assert client.get("/readyz").json()["checks"] == {"database": "ok", "broker": "ok"}

    files = capture_files(synth_capture)
    capture = client.post("/v1/captures", json={"format": "canonical", "manifest": {"files": [
        {"path": p, "size": len(d), "sha256": hashlib.sha256(d).hexdigest()}
        for p, d in files.items()]}}).json()
    for path, data in files.items():
        upload_file(client, capture["id"], path, data)
    r = client.post(f"/v1/captures/{capture['id']}/commit")
    assert r.status_code == 200 and r.json()["state"] == "ready", r.text
    keys = {b.key for b in services.blobs.list(f"captures/{capture['id']}")}
    assert keys == {f"captures/{capture['id']}/{p}" for p in files}
    assert not services.staging.capture_dir(capture["id"]).exists()

    job = client.post("/v1/jobs", json={"capture_id": capture["id"],
                                        "params": {"preset": "test"}}).json()
    queued = redis.Redis.from_url(redis_url).lrange(f"{prefix}{settings.queue}", 0, -1)
    assert any(job["id"].encode() in message for message in queued)

    blob = bytes(range(256)) * 8
    src = tmp_path / "a.ply"
    src.write_bytes(blob)
    services.blobs.put_file(f"jobs/{job['id']}/artifacts/frames/000000/gaussians.ply", src)
    services.store.add_artifact(job["id"], "frames/000000/gaussians.ply", kind="ply",
                                size=len(blob), sha256=hashlib.sha256(blob).hexdigest(),
                                content_type="application/x-ply", frame="000000")
    url = f"/v1/jobs/{job['id']}/artifacts/frames/000000/gaussians.ply"
    part = client.get(url, headers={"Range": "bytes=100-299"})
    assert part.status_code == 206 and part.content == blob[100:300]
    assert client.get(url).content == blob
