"""A sequence job run as parts through the runner, one part after another in this process: each
part publishes its own frames into the job's artifacts, the job's assembly merges the records
(metrics.json, sequence.json listing every frame) and evaluates; the frames are bit-identical
to the same run made in one piece (groups are independent, one thread)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from worker_harness import add_capture, tiny_config

from worker.blobs import LocalBlobStore
from worker.runner import Runner
from worker.settings import WorkerSettings
from worker.store import JobStore

FRAMES = ("000000", "000001", "000002", "000003")


@pytest.fixture(scope="module")
def capture4(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from core.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("parts-job") / "capture"
    synthesize(out, SynthConfig(frames=4, views=8, width=32, height=32, seed=2, ao_directions=8))
    return out


def test_parts_assemble_into_the_run_made_in_one_piece(tmp_path: Path, capture4: Path):
    import torch

    from core.pipeline import reconstruct

    torch.set_num_threads(1)
    url = f"sqlite:///{tmp_path / 'dgs.sqlite3'}"
    from worker.db import migrate

    migrate(url)
    settings = WorkerSettings(data_dir=tmp_path / "data", database_url=url,
                              heartbeat_seconds=0.2, lease_seconds=30, torch_threads=1)
    store, blobs = JobStore(url), LocalBlobStore(tmp_path / "data" / "store")
    cap = add_capture(store, blobs, capture4)
    config = {**tiny_config(30), "sequence": {"num_nodes": 32}}
    config["mesh"] = {"enabled": False}
    params = {"preset": "test", "gop": 2, "config": config}
    parent, parts = store.create_parted("t1", "reconstruct", params,
                                        [list(FRAMES[:2]), list(FRAMES[2:])], capture_id=cap)
    runner = Runner(settings, store, blobs)
    assert runner.run(parts[1].id).status == "succeeded"  # in any order
    assert store.get(parent.id).state == "running"
    # The worker of the last part assembles the job at once.
    assert runner.run(parts[0].id).status == "succeeded"
    job = store.get(parent.id)
    assert job.state == "succeeded" and job.fraction == 1.0

    artifacts = tmp_path / "data" / "store" / "jobs" / parent.id / "artifacts"
    record = json.loads((artifacts / "sequence.json").read_text())
    assert [f["frame"] for f in record["frames"]] == list(FRAMES)
    assert all(f["done"] for f in record["frames"])
    assert [f["role"] for f in record["frames"]] == ["key", "deformed"] * 2
    assert list(json.loads((artifacts / "metrics.json").read_text())["frames"]) == list(FRAMES)
    assert {f["frame"] for f in json.loads((artifacts / "eval.json").read_text())[
        "per_frame"]} == set(FRAMES)
    assert not blobs.list(f"jobs/{parent.id}/parts")  # the parts' records are merged
    for part in parts:
        assert not blobs.list(f"jobs/{part.id}")  # nothing of a part is left

    serial = tmp_path / "serial"
    reconstruct(capture4, serial, preset="test", gop=2, overrides=config, progress=False)
    for frame in FRAMES:
        ply = f"frames/{frame}/gaussians.ply"
        assert (artifacts / ply).read_bytes() == (serial / ply).read_bytes(), frame
