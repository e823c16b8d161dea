"""The service path on a GPU (skipped without one): a part of a sequence job run by the
worker's runner on CUDA (`train.device` cuda), its frames published, its record saying where
it trained; the same part on the CPU gives frames of the same size."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from worker_harness import add_capture, tiny_config

from worker.blobs import LocalBlobStore
from worker.runner import Runner
from worker.settings import WorkerSettings
from worker.store import JobStore


def _cuda_ready() -> tuple[bool, str]:
    if not torch.cuda.is_available():
        return False, "no CUDA device (a CUDA worker is tested on a GPU machine)"
    from native._backend import has_cuda

    if not has_cuda():
        return False, "the native extension was built without CUDA (nvcc missing or DGS_CUDA=0)"
    return True, ""


_READY, _WHY = _cuda_ready()
pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not _READY, reason=_WHY)]
FRAMES = ("000000", "000001", "000002", "000003")


def test_a_part_runs_on_a_cuda_worker(tmp_path: Path):
    from core.synth import SynthConfig, synthesize
    from worker.db import migrate

    capture = tmp_path / "capture"
    synthesize(capture, SynthConfig(frames=4, views=8, width=32, height=32, seed=2,
                                    ao_directions=8))
    url = f"sqlite:///{tmp_path / 'dgs.sqlite3'}"
    migrate(url)
    settings = WorkerSettings(data_dir=tmp_path / "data", database_url=url,
                              heartbeat_seconds=0.2, lease_seconds=30, torch_threads=1,
                              devices="auto,cpu,cuda")
    store, blobs = JobStore(url), LocalBlobStore(tmp_path / "data" / "store")
    cap = add_capture(store, blobs, capture)
    config = {**tiny_config(30), "sequence": {"num_nodes": 32}, "mesh": {"enabled": False}}
    config["train"]["device"] = "cuda"
    parent, parts = store.create_parted("t1", "reconstruct",
                                        {"preset": "test", "gop": 2, "config": config},
                                        [list(FRAMES[:2]), list(FRAMES[2:])], capture_id=cap)
    runner = Runner(settings, store, blobs)
    assert runner.run(parts[0].id).status == "succeeded", [
        r.line for r in store.logs(parts[0].id, 0, 1000)]
    artifacts = tmp_path / "data" / "store" / "jobs" / parent.id / "artifacts"
    for frame in FRAMES[:2]:
        assert (artifacts / "frames" / frame / "gaussians.ply").is_file(), frame
    records = [json.loads(p.read_text()) for p in
               (tmp_path / "data" / "store" / "jobs" / parent.id / "parts").rglob("config.json")]
    assert records and all(r["train"]["device"] == "cuda:0" for r in records)
    assert runner.run(parts[1].id).status == "succeeded"  # and the job is assembled
    assert store.get(parent.id).state == "succeeded"
