"""A render request end to end on the deployment stack: the API (uvicorn on a loopback port) and
a real `dgs worker` process on PostgreSQL, Redis and S3 (moto's server over HTTP), driven with
service.client. A tiny capture is reconstructed, an EXR environment map uploaded, a relit orbit
rendered to a valid 4-frame MP4 and PNGs; a long render is cancelled mid-way and stops at its
next view, and its reconstruction cannot be deleted while it runs."""

from __future__ import annotations

import os
import re
import secrets
import socket
import threading
from pathlib import Path

import numpy as np
import pytest
import uvicorn
from test_celery import s3_server  # noqa: F401  (a fixture)
from worker_harness import tiny_config, wait_for

from service.app import create_app
from service.client import Client
from service.settings import ServiceSettings

pytestmark = pytest.mark.timeout(400)


@pytest.fixture
def stack(tmp_path: Path, pg_empty, redis_broker, s3_server, monkeypatch):  # noqa: F811
    """(environment of worker processes, the API's base URL)."""
    import boto3

    redis_url, prefix = redis_broker
    bucket = f"dgs-{secrets.token_hex(4)}"
    for key in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
        monkeypatch.setenv(key, "test")
    boto3.client("s3", endpoint_url=s3_server, region_name="us-east-1").create_bucket(
        Bucket=bucket)
    shared = {"database_url": pg_empty, "broker_url": redis_url, "redis_key_prefix": prefix,
              "queue": f"q-{secrets.token_hex(4)}", "storage_url": f"s3://{bucket}/dgs",
              "s3_endpoint_url": s3_server, "s3_region": "us-east-1"}
    env = {f"DGS_{k.upper()}": v for k, v in shared.items()}
    # The cancel grace (before a wedged job's process is ended) is far longer than a view, so
    # only the view boundary can stop a render (the wedged case: tests/worker/test_runner.py).
    env.update({"DGS_DATA_DIR": str(tmp_path / "worker"), "DGS_LEASE_SECONDS": "10",
                "DGS_HEARTBEAT_SECONDS": "0.3", "DGS_CANCEL_GRACE_SECONDS": "3600",
                "OMP_NUM_THREADS": "1", "AWS_ACCESS_KEY_ID": "test",
                "AWS_SECRET_ACCESS_KEY": "test"})
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("DGS_")}, **env}
    settings = ServiceSettings(_env_file=None, data_dir=tmp_path / "api", public_url=None,
                               retention_days=None, sse_poll_seconds=0.1, **shared)
    server = uvicorn.Server(uvicorn.Config(create_app(settings), log_level="warning"))
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    wait_for(lambda: server.started or not thread.is_alive(), 30, "the API to start")
    assert thread.is_alive()
    yield env, f"http://127.0.0.1:{sock.getsockname()[1]}"
    server.should_exit = True
    thread.join(timeout=10)
    sock.close()


def reconstruction(c: Client, capture: Path) -> str:
    cap = c.create_capture(capture)
    c.upload_capture(cap["id"], capture)
    c.commit(cap["id"])
    job = c.submit(cap["id"], {"preset": "test", "config": tiny_config(40)})
    job = c.wait(job["id"], timeout=240)
    assert job["state"] == "succeeded", c.logs(job["id"])
    return job["id"]


def test_a_render_runs_on_a_worker_to_an_mp4_and_a_cancel_stops_it(
        stack, tiny_capture: Path, worker_factory, tmp_path: Path):
    import cv2
    import imageio_ffmpeg

    env, base = stack
    worker_factory(env).start()
    c = Client(base, timeout=120)
    source = reconstruction(c, tiny_capture)
    envmap = c.upload_envmap(tiny_capture / "gt" / "envmaps" / "relight.exr")
    assert (envmap["kind"], envmap["content_type"]) == ("envmap", "image/x-exr")

    render = c.render(source, envmap["id"], orbit=4, rotation_deg=30, lights=[
        {"kind": "directional", "direction": [0, -1, 0], "intensity": 2.0}])
    assert render["pipeline"] == "relight" and render["source_job_id"] == source
    events = []
    done = c.wait(render["id"], on_event=events.append, timeout=180)
    assert done["state"] == "succeeded", c.logs(render["id"])
    assert done["progress"]["iterations"] == 4 and done["progress"]["fraction"] == 1.0
    fractions = [e.data["fraction"] for e in events if "fraction" in e.data]
    assert fractions == sorted(fractions)
    items = {a["path"]: a for a in c.artifacts(render["id"])}
    assert items["relit/000000.mp4"]["kind"] == "video"
    assert items["relit/relight.json"]["kind"] == "relight"
    assert {a["kind"] for p, a in items.items() if p.startswith("relit/000000/")} == {"relit"}
    mp4 = c.download(render["id"], "relit/000000.mp4", tmp_path / "orbit.mp4",
                     sha256=items["relit/000000.mp4"]["sha256"])
    reader = imageio_ffmpeg.read_frames(str(mp4))
    meta = next(reader)
    assert meta["codec"] == "h264" and len(list(reader)) == 4
    png = c.download(render["id"], "relit/000000/orbit002.png", tmp_path / "view.png",
                     sha256=items["relit/000000/orbit002.png"]["sha256"])
    image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert image.shape == (32, 32, 3) and np.ptp(image) > 20  # a subject, not a blank frame

    long = c.render(source, envmap["id"], orbit=720)
    wait_for(lambda: c.job(long["id"])["progress"]["iteration"] >= 2, 120,
             "the long render to draw views")
    refused = c.http.delete(f"/v1/jobs/{source}")  # its reconstruction is in use
    assert refused.status_code == 409 and long["id"] in refused.json()["error"]["message"]
    c.cancel(long["id"])
    stopped = c.wait(long["id"], timeout=300)
    assert stopped["state"] == "cancelled"
    assert stopped["progress"]["stage"] == "cancelled"
    assert 2 <= stopped["progress"]["iteration"] < 720
    logs = "\n".join(c.logs(long["id"]))
    # Stopped at a view boundary, not killed.
    assert re.search(r"cancelled: relight stopped after \d+ of 720 views", logs), logs
    assert "did not stop within" not in logs
    assert c.artifacts(long["id"]) == []
