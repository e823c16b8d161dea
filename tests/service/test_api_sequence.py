"""A sequence job through the HTTP API of a real `dgs serve` (API + embedded Celery worker): a
three-frame capture uploaded with the Python client, a reconstruct job of one group of pictures,
its server-sent events followed to the end. The events carry per-frame progress (each frame in
turn, the tracked frames' deform and refine stages, a fraction that never goes back), and the
artifacts list every frame's PLY, renders and mesh and the sequence record."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from live_server import LiveServer

from service.client import Client

pytestmark = pytest.mark.timeout(420)

FRAMES = ("000000", "000001", "000002")
TINY = {"train": {"schedule": {"iterations": 40, "stage2_start": 12, "stage3_start": 28,
                               "densify_from": 2, "densify_until": 24, "densify_interval": 4,
                               "reset_interval": 16, "sh_interval": 4}, "init_points": 300},
        "sequence": {"num_nodes": 64}}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("seq-api") / "data"
    live = LiveServer(data, data.parent / "serve.log").start()
    live.wait_worker()
    yield live
    live.stop()


def test_a_sequence_job_streams_per_frame_progress_and_lists_every_frame(server, tmp_path):
    from core.synth import SynthConfig, synthesize

    folder = tmp_path / "capture"
    synthesize(folder, SynthConfig(frames=3, views=8, width=32, height=32, seed=5,
                                   ao_directions=8))
    with Client(server.url) as client:
        cap = client.create_capture(folder)
        client.upload_capture(cap["id"], folder)
        assert client.commit(cap["id"], timeout=120)["state"] == "ready"
        job = client.submit(cap["id"], {"preset": "test", "gop": 3, "config": TINY})
        events = []
        done = client.wait(job["id"], events.append, timeout=360)
        assert done["state"] == "succeeded", "\n".join(client.logs(job["id"]))
        progress = [e.data for e in events if e.kind == "progress"]
        # Frame by frame, in order, each out of three; the tracked frames show their stages.
        frames = [p["frame"] for p in progress if p.get("frame")]
        assert frames == sorted(frames) and set(frames) == {1, 2, 3}, frames
        assert {p.get("frames") for p in progress if p.get("frames")} == {3}
        assert {p.get("stage") for p in progress if p.get("frame", 0) > 1} & {"deform", "refine"}
        fractions = [p["fraction"] for p in progress]
        assert fractions == sorted(fractions) and done["progress"]["fraction"] == 1.0
        listed = {a["path"]: a for a in client.artifacts(job["id"])}
        for frame in FRAMES:
            for path in (f"frames/{frame}/gaussians.ply", f"renders/{frame}/cam00_rgb.png",
                         f"renders/{frame}/cam00_normal.png", f"meshes/{frame}.ply"):
                assert path in listed, (path, sorted(listed))
            assert listed[f"frames/{frame}/gaussians.ply"]["frame"] == frame
        client.download(job["id"], "sequence.json", tmp_path / "sequence.json")
        record = json.loads(Path(tmp_path / "sequence.json").read_text())
        assert [f["frame"] for f in record["frames"]] == list(FRAMES)
        assert [f["role"] for f in record["frames"]] == ["key", "deformed", "deformed"]
        assert all(f["done"] for f in record["frames"])
