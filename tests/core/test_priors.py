"""core.priors: TorchScript (and optional ONNX) normal estimators, filling views without a
prior, and training with no prior at all."""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from core.config import read_run
from core.data import CaptureDataset, load_capture
from core.pipeline import reconstruct
from core.priors import TorchScriptNormalEstimator, fill_priors, load_estimator
from core.synth import SynthConfig, synthesize
from core.training import View, training_cameras

# Tiny tensors: a second intra-op thread only adds synchronisation.
pytestmark = pytest.mark.usefixtures("one_thread")

SHORT = {"train": {"schedule": {"iterations": 100, "stage2_start": 30, "stage3_start": 70,
                                "densify_from": 5, "densify_until": 60, "densify_interval": 10,
                                "reset_interval": 40, "sh_interval": 10}, "init_points": 500}}


class Facing(torch.nn.Module):
    """Every pixel's normal points back at the camera (-z in OpenCV camera axes), scaled by 2
    so that the estimator's normalisation is exercised."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = torch.zeros_like(x)
        out[:, 2] = -2.0
        return out


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """No normals/ folder: the priors must come from elsewhere or stay off."""
    out = tmp_path_factory.mktemp("priors") / "capture"
    synthesize(out, SynthConfig(frames=1, views=8, width=24, height=24, seed=5, priors=False,
                                ao_directions=4))
    return out


@pytest.fixture(scope="module")
def model_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("model") / "facing.pt"
    with warnings.catch_warnings():  # TorchScript is deprecated in torch 2.x, still shipped
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.script(Facing()).save(str(path))
    return path


def _views(capture: Path) -> list[View]:
    cap = load_capture(capture)
    ds = CaptureDataset(cap, cameras=[c.id for c in training_cameras(cap)])
    return [View.from_sample(ds[i]) for i in range(len(ds))]


def test_torchscript_estimator(model_file: Path):
    est = load_estimator(model_file)
    assert isinstance(est, TorchScriptNormalEstimator) and est.space == "camera"
    n = est(np.random.default_rng(0).random((5, 7, 3)).astype(np.float32))
    assert n.shape == (5, 7, 3) and n.dtype == np.float32
    assert np.allclose(n, [0.0, 0.0, -1.0])  # unit length


def test_fill_priors_rotates_camera_normals_to_world(capture: Path, model_file: Path):
    views = _views(capture)
    assert all(v.normal is None for v in views)
    assert fill_priors(views, load_estimator(model_file)) == "estimator"
    for v in views:
        R = np.asarray(v.camera.world_to_camera)[:3, :3]
        # Camera -z in world is minus the camera's forward row of R.
        assert np.allclose(v.normal.numpy(), -R[2], atol=1e-5)
        assert v.normal.shape == v.image.shape
    world = _views(capture)
    fill_priors(world, load_estimator(model_file, space="world"))
    assert np.allclose(world[0].normal.numpy(), [0.0, 0.0, -1.0])


def test_fill_priors_keeps_capture_priors_and_reports_off(capture: Path, model_file: Path):
    views = _views(capture)
    assert fill_priors(views, None) == "off"
    assert all(v.normal is None for v in views)
    views[0].normal = torch.zeros_like(views[0].image)
    kept = views[0].normal
    assert fill_priors(views, load_estimator(model_file)) == "mixed"
    assert views[0].normal is kept and views[1].normal is not None
    assert load_estimator(None) is None and load_estimator("") is None


def test_estimator_errors_name_the_file(tmp_path: Path):
    with pytest.raises(ValueError, match="nope.pt not found"):
        load_estimator(tmp_path / "nope.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a model")
    with pytest.raises(ValueError, match="junk.pt is not a TorchScript file"):
        load_estimator(junk)


def test_onnx_without_onnxruntime_says_what_to_install(tmp_path: Path, monkeypatch):
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # `import onnxruntime` fails
    (tmp_path / "m.onnx").write_bytes(b"")
    with pytest.raises(ValueError, match="onnxruntime is not installed"):
        load_estimator(tmp_path / "m.onnx")


def test_onnx_estimator(tmp_path: Path):
    # onnxruntime is in the `train` extra and onnx (to export the model) in `dev`.
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    path = tmp_path / "facing.onnx"
    with warnings.catch_warnings():  # the TorchScript-based exporter (no onnxscript needed)
        warnings.simplefilter("ignore")
        torch.onnx.export(Facing(), (torch.zeros(1, 3, 4, 4),), str(path), dynamo=False,
                          dynamic_axes={"x": {2: "h", 3: "w"}}, input_names=["x"])
    n = load_estimator(path)(np.zeros((6, 5, 3), np.float32))
    assert np.allclose(n, [0.0, 0.0, -1.0])


def _run(capture: Path, tmp_path: Path, extra: dict) -> dict:
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({**SHORT, **extra}))
    return reconstruct(capture, tmp_path / "run", preset="test", config_file=cfg,
                       progress=False)["frames"]["000000"]


def test_without_priors_the_rig_gives_them(capture: Path, tmp_path: Path):
    """No normals/ and no estimator: the key frame's fused depth and hull give the priors
    (the default), timed in its record."""
    f = _run(capture, tmp_path, {})
    assert f["normal_prior"] == "rig" and "normal" in f["final_losses"]
    assert f["rig_seconds"]["priors"] > 0 and any(n.startswith("rig geometry") for n in
                                                  f["notes"])


def test_without_priors_training_still_runs(capture: Path, tmp_path: Path):
    f = _run(capture, tmp_path, {"rig_priors": False})
    assert f["normal_prior"] == "off"
    assert "normal" not in f["final_losses"]
    # The depth-normal consistency and visibility terms still ran.
    assert {"consistency", "visibility", "photometric"} <= set(f["final_losses"])
    assert (tmp_path / "run" / "renders" / "000000" / "cam00_normal.png").is_file()


def test_estimator_named_in_configuration(capture: Path, model_file: Path, tmp_path: Path):
    f = _run(capture, tmp_path, {"normal_estimator": str(model_file)})
    assert f["normal_prior"] == "estimator" and "normal" in f["final_losses"]
    assert read_run(tmp_path / "run").config.normal_estimator == str(model_file)
