"""A sequence job run as parts by a real `dgs worker` on the distributed stack (PostgreSQL, Redis,
S3 over HTTP): the parts go through Redis, each publishes its frames to S3, the last one sends
the job for its assembly, which reads them back and writes sequence.json over every frame."""

from __future__ import annotations

import json
import os
import secrets
from pathlib import Path

import pytest
from worker_harness import add_capture, tiny_config, wait_for

from worker.blobs import open_store
from worker.celery_app import dispatch, make_celery
from worker.db import migrate
from worker.settings import WorkerSettings
from worker.store import JobStore

pytestmark = pytest.mark.timeout(600)
FRAMES = ["000000", "000001", "000002", "000003"]


@pytest.fixture(scope="module")
def capture4(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from core.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("parts-celery") / "capture"
    synthesize(out, SynthConfig(frames=4, views=8, width=32, height=32, seed=3, ao_directions=8))
    return out


def test_parts_through_redis_and_s3(tmp_path: Path, monkeypatch, pg_empty, redis_broker,
                                    capture4: Path, worker_factory):
    import boto3
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0)
    server.start()
    try:
        host, port = server.get_host_and_port()
        endpoint, bucket = f"http://{host}:{port}", f"dgs-{secrets.token_hex(4)}"
        redis_url, prefix = redis_broker
        env = {"DGS_DATA_DIR": str(tmp_path / "data"), "DGS_LEASE_SECONDS": "4",
               "DGS_HEARTBEAT_SECONDS": "0.5", "DGS_QUEUE": f"q-{secrets.token_hex(4)}",
               "DGS_SHARE_AFTER_SECONDS": "0",  # as test_celery's stack: the shared store
               "OMP_NUM_THREADS": "1", "DGS_DATABASE_URL": pg_empty, "DGS_BROKER_URL": redis_url,
               "DGS_REDIS_KEY_PREFIX": prefix, "DGS_STORAGE_URL": f"s3://{bucket}/dgs",
               "DGS_S3_ENDPOINT_URL": endpoint, "DGS_S3_REGION": "us-east-1",
               "AWS_ACCESS_KEY_ID": "test", "AWS_SECRET_ACCESS_KEY": "test"}
        boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1",
                     aws_access_key_id="test", aws_secret_access_key="test",
                     ).create_bucket(Bucket=bucket)
        for key, value in env.items():
            monkeypatch.setenv(key, value)
        settings = WorkerSettings()
        migrate(settings.database)
        store = JobStore(settings.database)
        blobs = open_store(settings.storage, endpoint_url=endpoint, region="us-east-1")
        cap = add_capture(store, blobs, capture4, capture_id=f"cap_{secrets.token_hex(4)}")
        config = {**tiny_config(30), "sequence": {"num_nodes": 32}, "mesh": {"enabled": False}}
        parent, parts = store.create_parted(
            "t1", "reconstruct", {"preset": "test", "gop": 2, "config": config},
            [FRAMES[:2], FRAMES[2:]], capture_id=cap)
        worker_factory({**os.environ, **env}).start()
        celery = make_celery(settings)
        for part in parts:
            store.mark_dispatched(part.id)
            dispatch(celery, settings, part.id, "reconstruct")
        job = wait_for(lambda: (j := store.get(parent.id)).state in (
            "succeeded", "failed", "cancelled") and j, 300, "the job to end")
        logs = "\n".join(r.line for p in [parent, *parts] for r in store.logs(p.id, 0, 1000))
        assert job.state == "succeeded", logs
        key = f"jobs/{parent.id}/artifacts/sequence.json"
        record = json.loads(b"".join(blobs.read_range(key, 0, 1 << 30)))
        assert [f["frame"] for f in record["frames"]] == FRAMES
        assert all(f["done"] for f in record["frames"])
        assert [p.state for p in store.parts(parent.id)] == ["succeeded", "succeeded"]
    finally:
        server.stop()
