"""core.evaluation.evaluate_run on hand-made runs (renders copied from the ground truth, then
spoiled) and on a short real reconstruction."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from core.config import load_config, resolve_run
from core.data import load_capture
from core.evaluation import evaluate_run
from core.metrics import normal_agreement, rgb_scores
from core.pipeline import reconstruct
from core.synth import SynthConfig, synthesize


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """9 views (two held out: cam00 and cam08), 24x24, one frame, priors and ground truth."""
    out = tmp_path_factory.mktemp("eval") / "capture"
    synthesize(out, SynthConfig(frames=1, views=9, width=24, height=24, seed=4, priors=True,
                                ao_directions=4))
    return out


def _png(path: Path, a: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)).save(path)


def fake_run(root: Path, capture: Path, normal=lambda gt: gt, rgb_noise: float = 0.0) -> Path:
    """A run whose held-out renders are the capture image and a function of the gt normals."""
    run = root / "run"
    run.mkdir(parents=True)
    resolved = resolve_run(load_capture(capture), load_config("test"), preset="test",
                           frames="0:1")  # background black; cam00 and cam08 held out
    (run / "config.json").write_text(json.dumps(resolved.to_json()))
    (run / "metrics.json").write_text(json.dumps({"frames": {"000000": {}}}))
    rng = np.random.default_rng(0)
    for cam in ("cam00", "cam08"):
        img = np.asarray(Image.open(capture / "images" / "000000" / f"{cam}.png"))[..., :3] / 255
        mask = np.asarray(Image.open(capture / "masks" / "000000" / f"{cam}.png")) / 255
        img = img * (mask[..., None] if mask.ndim == 2 else mask[..., :1])
        _png(run / "renders" / "000000" / f"{cam}_rgb.png",
             img + rgb_noise * rng.standard_normal(img.shape))
        gt = np.load(capture / "gt" / "normals" / "000000" / f"{cam}.npy")
        fg = np.linalg.norm(gt, axis=-1, keepdims=True) > 0.5
        _png(run / "renders" / "000000" / f"{cam}_normal.png",
             np.where(fg, (normal(gt) + 1) / 2, 0.0))
    return run


def test_perfect_renders_score_perfectly(capture: Path, tmp_path: Path):
    result = evaluate_run(fake_run(tmp_path, capture))
    assert result == json.loads((tmp_path / "run" / "eval.json").read_text())
    assert result["views"] == 2 and [v["camera"] for v in result["per_frame"][0]["views"]] == [
        "cam00", "cam08"]
    # The capture is straight colour times coverage; an 8-bit render of that product is off by
    # at most half a level on the silhouette (54 dB), and exact elsewhere.
    assert result["psnr"] > 54 and result["ssim"] == pytest.approx(1.0, abs=1e-4)
    assert result["normal_reference"] == "ground truth"
    assert result["normal_cos"] > 0.995 and result["normal_deg"] < 5.0  # 8-bit quantisation
    assert result["lpips"] is None and result["chamfer"] is None


def test_spoiled_renders_score_worse(capture: Path, tmp_path: Path):
    flipped = evaluate_run(fake_run(tmp_path / "a", capture, normal=lambda gt: -gt))
    assert flipped["normal_cos"] < -0.99 and flipped["normal_deg"] > 175
    blank = evaluate_run(fake_run(tmp_path / "b", capture, normal=lambda gt: 0 * gt - 1))
    # (n+1)/2 of -1 is black: nothing drawn, which counts as cosine 0 (90 degrees).
    assert blank["normal_cos"] == pytest.approx(0.0) and blank["normal_deg"] == pytest.approx(90)
    noisy = evaluate_run(fake_run(tmp_path / "c", capture, rgb_noise=0.05))
    assert 20 < noisy["psnr"] < 35 and noisy["ssim"] < 0.95
    # Noise everywhere: the whole image scores about as the figure; both far from perfect.
    assert abs(noisy["psnr_full"] - noisy["psnr"]) < 3


def test_normal_reference_falls_back_to_priors_then_null(capture: Path, tmp_path: Path):
    run = fake_run(tmp_path, capture)
    no_gt = tmp_path / "no_gt"
    shutil.copytree(capture, no_gt, ignore=shutil.ignore_patterns("gt"))
    result = evaluate_run(run, no_gt)
    assert result["normal_reference"] == "prior" and result["capture"] == str(no_gt)
    # The priors are degraded ground truth: agreement is good but not perfect.
    assert 0.5 < result["normal_cos"] < 0.999
    shutil.rmtree(no_gt / "normals")
    result = evaluate_run(run, no_gt)
    assert result["normal_cos"] is None and result["normal_deg"] is None
    assert result["psnr"] > 54


def test_bad_inputs(capture: Path, tmp_path: Path):
    with pytest.raises(ValueError, match="not a run directory"):
        evaluate_run(tmp_path)
    run = fake_run(tmp_path, capture)
    with pytest.raises(ValueError, match="capture"):
        evaluate_run(run, tmp_path / "nowhere")
    (run / "renders" / "000000" / "cam08_rgb.png").unlink()
    with pytest.raises(ValueError, match="cam08_rgb.png"):
        evaluate_run(run)


def test_normal_agreement_counts_only_foreground():
    ref = np.zeros((2, 2, 3), np.float32)
    ref[..., 2] = 1
    pred = np.zeros((2, 2, 3), np.float32)
    pred[0, 0] = [0.5, 0.5, 1.0]  # +z
    fg = np.array([[True, False], [False, False]])
    assert normal_agreement(pred, ref, fg) == pytest.approx((1.0, 0.0), abs=1e-3)
    assert normal_agreement(pred, ref, np.zeros((2, 2), bool)) is None


def test_a_view_without_foreground_has_no_psnr_and_is_left_out_of_the_means():
    from core.evaluation.run import _summary

    rng = np.random.default_rng(0)
    rgb, target = rng.uniform(size=(2, 8, 8, 3)).astype(np.float32)
    empty = rgb_scores(rgb, target, np.zeros((8, 8), bool))
    assert empty["psnr"] is None  # not 100 dB: there was nothing to score
    assert math.isfinite(empty["psnr_full"]) and empty["psnr_full"] < 20
    full = rgb_scores(rgb, target, np.ones((8, 8), bool))
    assert full["psnr"] == pytest.approx(full["psnr_full"])
    perfect = rgb_scores(target, target, np.ones((8, 8), bool))
    assert perfect["psnr"] == 100.0  # a perfect match still scores the cap
    mean = _summary([{**empty, "normal_cos": None, "normal_deg": None},
                     {**full, "normal_cos": None, "normal_deg": None}])
    assert mean["psnr"] == pytest.approx(full["psnr"])  # the empty view is skipped
    assert mean["psnr_full"] == pytest.approx((empty["psnr_full"] + full["psnr_full"]) / 2)
    assert _summary([{**empty, "normal_cos": None, "normal_deg": None}])["psnr"] is None


def test_real_run(capture: Path, tmp_path: Path):
    torch_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        short = tmp_path / "short.json"
        short.write_text(json.dumps({"train": {"schedule": {
            "iterations": 100, "stage2_start": 30, "stage3_start": 70, "densify_from": 5,
            "densify_until": 60, "densify_interval": 10, "reset_interval": 40,
            "sh_interval": 10}, "init_points": 500}}))
        reconstruct(capture, tmp_path / "run", preset="test", config_file=short, progress=False)
    finally:
        torch.set_num_threads(torch_threads)
    result = evaluate_run(tmp_path / "run")
    assert result["views"] == 2
    assert 10 < result["psnr"] < 40 and 0 < result["ssim"] < 1
    # 100 steps on 7 training views of 24x24 generalise poorly to a held-out view's normals:
    # check only that the numbers are scored against the ground truth and consistent.
    assert result["normal_reference"] == "ground truth"
    assert -1 <= result["normal_cos"] <= 1 and 0 <= result["normal_deg"] <= 180
    assert [f["frame"] for f in result["per_frame"]] == ["000000"]


def test_eval_scores_lpips_offline(tmp_path: Path):
    """LPIPS (AlexNet) on 48 px views (AlexNet needs 31), from the pinned weights the venv
    installs: no environment variable, no download."""
    capture = tmp_path / "capture"
    synthesize(capture, SynthConfig(frames=1, views=9, width=48, height=48, seed=4, priors=True,
                                    ao_directions=4))
    exact = evaluate_run(fake_run(tmp_path / "b", capture))
    noisy = evaluate_run(fake_run(tmp_path / "c", capture, rgb_noise=0.2))
    # 8-bit renders of the target itself are near 0; noise of 0.2 is far.
    assert exact["lpips"] is not None and 0 <= exact["lpips"] < 0.02
    assert noisy["lpips"] > exact["lpips"] + 0.1
    assert all(v["lpips"] is not None for v in noisy["per_frame"][0]["views"])
