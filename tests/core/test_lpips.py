"""LPIPS: the network against hand-checked properties, and its place in `dgs eval` when trunk
weights are given (a randomly initialised AlexNet saved by the test: the number means nothing,
the plumbing does)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from core.evaluation.lpips import ENV, Lpips, lin_weights, load_lpips


@pytest.fixture
def trunk(tmp_path: Path) -> Path:
    """A random AlexNet state dict under torchvision's names (classifier keys too, ignored)."""
    torch.manual_seed(0)
    net = Lpips()
    state = {f"features.{k}": v.clone() for k, v in net.features.state_dict().items()}
    state["classifier.1.weight"] = torch.zeros(4, 4)
    path = tmp_path / "alexnet.pth"
    torch.save(state, path)
    return path


def test_lin_weights_ship_with_the_lpips_package():
    path = lin_weights()
    assert path is not None, "pip install --no-deps lpips==0.1.4 (make test does)"
    lins = torch.load(path, map_location="cpu", weights_only=True)
    assert [tuple(lins[f"lin{i}.model.1.weight"].shape) for i in range(5)] == [
        (1, 64, 1, 1), (1, 192, 1, 1), (1, 384, 1, 1), (1, 256, 1, 1), (1, 256, 1, 1)]


def test_distance_properties(trunk: Path):
    lp = load_lpips(trunk)
    rng = np.random.default_rng(0)
    a = rng.random((64, 80, 3)).astype(np.float32)
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1).astype(np.float32)
    c = np.clip(a + 0.05 * rng.standard_normal(a.shape), 0, 1).astype(np.float32)
    assert lp.score(a, a) == pytest.approx(0.0, abs=1e-7)
    assert lp.score(a, b) == pytest.approx(lp.score(b, a), rel=1e-5)
    assert lp.score(a, b) > lp.score(a, c) > 0  # more noise, farther
    # The linear layers are non-negative (calibrated that way), so the distance is too.
    assert all(float(lin.weight.min()) >= 0 for lin in lp.lins)


def test_no_trunk_no_lpips_and_bad_files_are_named(tmp_path: Path, monkeypatch):
    monkeypatch.delenv(ENV, raising=False)
    assert load_lpips() is None
    bad = tmp_path / "junk.pth"
    bad.write_bytes(b"not torch")
    with pytest.raises(ValueError, match="junk.pth"):
        load_lpips(bad)
    torch.save({"features.0.weight": torch.zeros(1)}, tmp_path / "half.pth")
    with pytest.raises(ValueError, match="not an AlexNet state dict"):
        load_lpips(tmp_path / "half.pth")


def test_images_too_small_for_alexnet_have_no_score(trunk: Path):
    lp = load_lpips(trunk)
    small = np.zeros((24, 24, 3), np.float32)
    assert lp.score(small, small) is None
    assert lp.score(np.zeros((31, 40, 3), np.float32), np.ones((31, 40, 3), np.float32)) > 0
