"""A multi-frame reconstruct job (one GoP: a key frame, then deformed frames) through the runner:
progress is reported per frame with the deform / refine stages, and the artifacts list every
frame's PLY and renders and the sequence record."""

from __future__ import annotations

from pathlib import Path

import pytest
from worker_harness import add_capture, tiny_config

from worker.blobs import LocalBlobStore
from worker.runner import Runner
from worker.settings import WorkerSettings
from worker.store import JobStore

FRAMES = ("000000", "000001", "000002")


@pytest.fixture(scope="module")
def capture3(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from core.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("seq-job") / "capture"
    synthesize(out, SynthConfig(frames=3, views=8, width=32, height=32, seed=2, ao_directions=8))
    return out


def test_a_sequence_job_reports_each_frame_and_lists_every_frame(tmp_path: Path, store_url: str,
                                                                 capture3: Path):
    settings = WorkerSettings(data_dir=tmp_path / "data", database_url=store_url,
                              heartbeat_seconds=0.2, lease_seconds=30)
    store = JobStore(store_url)
    blobs = LocalBlobStore(settings.data_dir / "store")
    cap = add_capture(store, blobs, capture3)
    config = tiny_config(40)
    config["sequence"] = {"num_nodes": 64}
    job = store.create("t1", "reconstruct", {"preset": "test", "gop": 3, "config": config},
                       capture_id=cap)
    assert Runner(settings, store, blobs).run(job.id).status == "succeeded"
    keys = {b.key.split("/artifacts/", 1)[1] for b in blobs.list(f"jobs/{job.id}/artifacts")}
    for frame in FRAMES:
        assert f"frames/{frame}/gaussians.ply" in keys
        assert f"renders/{frame}/cam00_rgb.png" in keys
        assert f"renders/{frame}/cam00_normal.png" in keys
    assert {"sequence.json", "metrics.json", "eval.json"} <= keys
    from sqlalchemy import select

    from worker.models import Artifact

    with store.session(write=False) as s:
        listed = {(a.path, a.frame) for a in s.scalars(select(Artifact).where(
            Artifact.job_id == job.id))}
    assert {(f"frames/{f}/gaussians.ply", f) for f in FRAMES} <= listed
    progress = [e.data for e in store.events_after(job.id, 0) if e.kind == "progress"]
    assert {p.get("frame") for p in progress} >= {1, 2, 3}
    assert {p.get("frames") for p in progress if p.get("frames")} == {3}
    # Progress is sampled by the heartbeat: a deformed frame shows at least one of its stages.
    assert {p.get("stage") for p in progress} & {"deform", "refine"}
    fractions = [p["fraction"] for p in progress]
    assert fractions == sorted(fractions)
