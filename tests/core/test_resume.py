"""`dgs reconstruct --resume` after a SIGKILL: the run continues from its last checkpoint and ends
bit-identical to an uninterrupted one (CPU, one thread in every process)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from core.model import GaussianModel
from core.synth import SynthConfig, synthesize

# Every stage (densification with splits, a reset, the AO bake at 100) in 150 steps; the first
# checkpoint at step 20 leaves most of the run to be killed in.
CONFIG = {"train": {"schedule": {"iterations": 150, "stage2_start": 45, "stage3_start": 100,
                                 "densify_from": 5, "densify_until": 90, "densify_interval": 10,
                                 "reset_interval": 60, "sh_interval": 15},
                    "init_points": 500},
          "checkpoint_every": 20}


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("resume")
    synthesize(root / "capture", SynthConfig(frames=1, views=8, width=32, height=32, seed=5,
                                             priors=True, ao_directions=8))
    (root / "config.json").write_text(json.dumps(CONFIG))
    return root / "capture", root / "config.json"


def _dgs(capture: Path, config: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "core.cli", "reconstruct", str(capture), "--out", str(out),
            "--preset", "test", "--config", str(config), *extra]


def _env() -> dict[str, str]:
    # One intra-op thread: the reductions of a step then always add in the same order.
    return {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _run(cmd: list[str]) -> str:
    done = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return done.stderr


def test_sigkilled_run_resumes_to_the_same_parameters(setup: tuple[Path, Path], tmp_path: Path):
    capture, config = setup
    straight = tmp_path / "straight"
    _run(_dgs(capture, config, straight, "--no-progress"))

    killed = tmp_path / "killed"
    ckpt = killed / "checkpoints" / "000000.pt"
    proc = subprocess.Popen(_dgs(capture, config, killed), env=_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 300
        while not ckpt.is_file() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert ckpt.is_file(), "no checkpoint appeared"
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL  # killed mid-run, not finished
    assert not (killed / "frames" / "000000" / "gaussians.ply").exists()
    saved_at = torch.load(ckpt, weights_only=True)["step"]
    assert 20 <= saved_at < 150

    # stderr is a pipe, not a terminal: progress comes as timed lines instead of a bar.
    log = _run(_dgs(capture, config, killed, "--resume"))
    assert f"frame 000000 (1/1): resumed at step {saved_at}/150" in log
    assert "frame 000000 (1/1): step 150/150 stage 3 loss " in log
    assert "\r" not in log  # no bar
    metrics = json.loads((killed / "metrics.json").read_text())["frames"]["000000"]
    assert metrics["resumed_at"] == saved_at
    a = GaussianModel.load_ply(straight / "frames" / "000000" / "gaussians.ply")
    b = GaussianModel.load_ply(killed / "frames" / "000000" / "gaussians.ply")
    assert len(a) == len(b)
    for name, p in a.params.items():
        assert torch.equal(b.params[name], p), name
    for png in sorted((straight / "renders" / "000000").glob("*.png")):
        assert (killed / "renders" / "000000" / png.name).read_bytes() == png.read_bytes()
