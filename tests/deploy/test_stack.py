"""The deployment brought up for real (`make deploy-test`): deploy/'s images built from a Debian
bookworm base made by debootstrap, its stack started with two CPU workers, and driven through
the API's published port as a studio would: a capture uploaded by tus, reconstructed on a worker
container and followed by server-sent events, its artifacts downloaded and checked, a relight
rendered; a sequence of two groups run as parts on both workers, one of them killed mid-part;
the API container restarted; PostgreSQL stopped; Redis restarted with a job in its queue.

Tiny jobs (32x32 synthetic captures, the `test` preset, few steps): what is checked is the
deployment, not the method."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from compose_stack import Stack, wait_for
from deploy_jobs import worker_hosts
from plyfile import PlyData

from service.client import Client

pytestmark = pytest.mark.timeout(3600)  # the first test waits for the images to build


def test_every_service_runs_from_the_images_built_here(stack: Stack):
    running = {s: stack.containers(s) for s in ("api", "worker", "redis", "postgres", "s3")}
    assert {s: len(c) for s, c in running.items()} == {
        "api": 1, "worker": 2, "redis": 1, "postgres": 1, "s3": 1}
    bucket = stack.containers("s3-bucket", all=True)
    assert [(c["State"], c["ExitCode"]) for c in bucket] == [("exited", 0)]
    # The API is published on loopback only (DGS_API_BIND's default), and healthy.
    (api,) = running["api"]
    assert stack.docker("port", api["ID"], "8000").stdout.split() == [f"127.0.0.1:{stack.port}"]
    # Docker runs the first health check one interval (15 s) after the start, whatever /readyz
    # already answers, so it is waited for rather than read once.
    def health(container: str = api["ID"]) -> str:
        return stack.docker("inspect", "-f", "{{.State.Health.Status}}",
                            container).stdout.strip()

    wait_for(lambda: health() != "starting", 300, "Docker's first health check of the API")
    assert health() == "healthy"
    # The API image has no torch; the worker image has the native extension built in.
    api = stack.exec("api", "python", "-c", "import torch", check=False)
    assert api.returncode != 0 and "No module named 'torch'" in api.stderr
    built = stack.exec("worker", "python", "-c", "import native._backend as b; "
                       "print((b.build_dir() / b.fingerprint() / 'built').is_file())")
    assert built.stdout.strip() == "True"
    # The broker neither loses nor evicts messages.
    assert stack.redis("CONFIG", "GET", "appendonly").split()[-1].strip('"') == "yes"
    assert stack.redis("CONFIG", "GET", "maxmemory-policy").split()[-1].strip('"') == \
        "noeviction"


def test_a_capture_sent_by_tus_is_reconstructed_on_a_worker_container(
        stack: Stack, client: Client, reconstruction: dict, tmp_path: Path):
    r = reconstruction
    folder, job = r["folder"], r["job"]
    declared = r["capture"]["total_bytes"]
    assert r["sent"] == declared > 0 and r["capture"]["state"] == "ready"
    assert job["state"] == "succeeded", "\n".join(r["logs"])
    assert job["worker"].split("/")[0] in worker_hosts(stack)  # ran in a worker container
    # Followed by server-sent events: it ran, progressed and ended, each event once.
    states = [e.data["state"] for e in r["events"] if e.kind == "state"]
    assert states[0] in ("queued", "running") and states[-1] == "succeeded"
    assert "running" in states
    fractions = [e.data["fraction"] for e in r["events"] if "fraction" in e.data]
    assert fractions and fractions == sorted(fractions)
    ids = [e.id for e in r["events"] if e.id]
    assert ids == sorted(set(ids))
    # Every artifact downloads and matches its SHA-256 (the client checks each).
    files = client.download_all(job["id"], tmp_path / "run")
    listed = {a["path"] for a in client.artifacts(job["id"])}
    assert {p.relative_to(tmp_path / "run").as_posix() for p in files} == listed
    ply = PlyData.read(str(tmp_path / "run" / "frames" / "000000" / "gaussians.ply"))
    assert ply["vertex"].count > 0 and np.isfinite(ply["vertex"]["x"]).all()
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["frames"]["000000"]["resumed_at"] == 0
    assert (folder / "capture.json").is_file()


def test_a_relight_renders_on_a_worker_container(client: Client, reconstruction: dict,
                                                 tmp_path: Path):
    import cv2
    import imageio_ffmpeg

    source = reconstruction["job"]["id"]
    envmap = client.upload_envmap(reconstruction["folder"] / "gt" / "envmaps" / "relight.exr")
    render = client.render(source, envmap["id"], orbit=4, rotation_deg=30, lights=[
        {"kind": "directional", "direction": [0, -1, 0], "intensity": 2.0}])
    done = client.wait(render["id"], timeout=900)
    assert done["state"] == "succeeded", client.logs(render["id"])
    items = {a["path"]: a for a in client.artifacts(render["id"])}
    mp4 = client.download(render["id"], "relit/000000.mp4", tmp_path / "orbit.mp4",
                          sha256=items["relit/000000.mp4"]["sha256"])
    reader = imageio_ffmpeg.read_frames(str(mp4))
    assert next(reader)["codec"] == "h264" and len(list(reader)) == 4
    png = client.download(render["id"], "relit/000000/orbit002.png", tmp_path / "view.png",
                          sha256=items["relit/000000/orbit002.png"]["sha256"])
    image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert image.shape == (32, 32, 3) and np.ptp(image) > 20  # a subject, not a blank frame
