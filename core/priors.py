"""Normal priors for training (docs/design.md section 5, "Normal prior").

A view's prior comes from the capture's normals/ folder (the dataset serves it, in world space),
or else from a pluggable estimator named in configuration: a model file that maps an image to
normals, or else from the calibrated rig: the key frame's stereo depth fused across its views
gives each view the normals of planes fitted to it, with a confidence (`core.rig`,
`RunConfig.rig_priors`). With none, the prior term stays off (the trainer skips it for views
without a prior) and the depth-normal consistency term still runs.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Literal, Protocol

import numpy as np
import torch

__all__ = [
    "NormalEstimator",
    "OnnxNormalEstimator",
    "TorchScriptNormalEstimator",
    "fill_priors",
    "load_estimator",
]

Space = Literal["camera", "world"]


class NormalEstimator(Protocol):
    """(H, W, 3) float image in 0..1 -> (H, W, 3) unit normals in `space` (camera space uses
    OpenCV axes: x right, y down, z forward)."""

    space: Space

    def __call__(self, image: np.ndarray) -> np.ndarray: ...


def _unit(n: np.ndarray, where: str) -> np.ndarray:
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"{where}: expected (H, W, 3) normals, got shape {n.shape}")
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    # Near-zero vectors mean "no estimate", as in the dataset's decoded priors.
    return np.where(norm > 0.1, n / np.maximum(norm, 1e-6), 0.0).astype(np.float32)


class TorchScriptNormalEstimator:
    """A TorchScript module taking a (1, 3, H, W) float image and returning (1, 3, H, W)
    normals (not necessarily unit length)."""

    def __init__(self, path: str | os.PathLike[str], space: Space = "camera"):
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"normal_estimator: model file {path} not found")
        if space not in ("camera", "world"):
            raise ValueError(f"normal_estimator_space: expected 'camera' or 'world', got {space!r}")
        try:
            with warnings.catch_warnings():
                # torch 2.x deprecates TorchScript in favour of torch.export, but scripted files
                # are what depth/normal estimators ship as today.
                warnings.simplefilter("ignore", DeprecationWarning)
                self.module = torch.jit.load(str(path), map_location="cpu").eval()
        except Exception as exc:  # torch raises RuntimeError subclasses with long C++ traces
            raise ValueError(f"normal_estimator: {path} is not a TorchScript file "
                             f"({str(exc).splitlines()[0]})") from None
        self.path, self.space = path, space

    @torch.no_grad()
    def __call__(self, image: np.ndarray) -> np.ndarray:
        x = torch.from_numpy(np.ascontiguousarray(image, np.float32)).permute(2, 0, 1)[None]
        out = self.module(x)
        if not isinstance(out, torch.Tensor) or out.shape != x.shape:
            raise ValueError(f"normal_estimator: {self.path} returned "
                             f"{getattr(out, 'shape', type(out))}, expected {tuple(x.shape)}")
        return _unit(out[0].permute(1, 2, 0).numpy(), str(self.path))


class OnnxNormalEstimator:
    """An ONNX model with the same contract as `TorchScriptNormalEstimator` (needs the optional
    `onnxruntime` package)."""

    def __init__(self, path: str | os.PathLike[str], space: Space = "camera"):
        try:
            # lazy: optional dependency, only for .onnx estimators
            import onnxruntime
        except ImportError:
            raise ValueError(f"normal_estimator: {path} is an ONNX file but onnxruntime is not "
                             "installed (pip install onnxruntime)") from None
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"normal_estimator: model file {path} not found")
        self.session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        self.path, self.space = path, space

    def __call__(self, image: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(image, np.float32).transpose(2, 0, 1)[None]
        name = self.session.get_inputs()[0].name
        out = np.asarray(self.session.run(None, {name: x})[0])
        return _unit(out[0].transpose(1, 2, 0), str(self.path))


def load_estimator(path: str | os.PathLike[str] | None,
                   space: Space = "camera") -> NormalEstimator | None:
    """The estimator named in configuration (`.onnx` -> ONNX, anything else TorchScript), or
    None when no path is configured."""
    if path is None or str(path) == "":
        return None
    if str(path).lower().endswith(".onnx"):
        return OnnxNormalEstimator(path, space)
    return TorchScriptNormalEstimator(path, space)


def fill_priors(views: Sequence, estimator: NormalEstimator | None, rig=None) -> str:
    """Give every `core.training.View` without a prior one from `estimator` (rotated to world
    space when it estimates camera-space normals), else from `rig` (a `core.rig.RigGeometry`
    of these views: normals, confidences and where they were measured), on the device of the
    view's image (both run on the CPU). Returns where the priors came from: 'capture',
    'estimator', 'rig', 'mixed' or 'off'."""
    have = sum(v.normal is not None for v in views)
    if estimator is None and rig is not None and have == 0 and views:
        for v, (n, c, measured) in zip(views, rig.priors()):
            v.normal = torch.from_numpy(n).to(v.image.device)
            v.normal_weight = torch.from_numpy(c).to(v.image.device)
            v.normal_measured = torch.from_numpy(measured).to(v.image.device)
        return "rig"
    if estimator is None or have == len(views):
        return "capture" if have == len(views) and views else ("mixed" if have else "off")
    for v in views:
        if v.normal is not None:
            continue
        n = estimator(v.image.cpu().numpy())
        if n.shape[:2] != tuple(v.image.shape[:2]):
            raise ValueError(f"normal_estimator: returned {n.shape[:2]} for a "
                             f"{tuple(v.image.shape[:2])} image")
        if estimator.space == "camera":
            # n_w = R^T n_c, as the dataset does for camera-space priors.
            n = n @ np.asarray(v.camera.world_to_camera, np.float32)[:3, :3]
        v.normal = torch.from_numpy(np.ascontiguousarray(n, np.float32)).to(v.image.device)
    return "estimator" if not have else "mixed"
