"""The canonical capture (docs/design.md section 3.1): typed cameras, frames and per-view file paths.

Parsing capture.json lives in :mod:`core.data.schema`, file-level checks (images exist, sizes
agree, ...) in :mod:`core.data.validate`.

This module must not import torch: the API process validates uploads with it.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from core.files import write_text
from core.data.points import POINTS_PLY
from core.data.rules import valid_name

__all__ = [
    "CAPTURE_JSON",
    "IMAGE_EXTS",
    "MASK_EXTS",
    "NORMAL_EXTS",
    "Camera",
    "Capture",
    "CaptureError",
    "Problem",
    "View",
    "save_capture",
    "valid_name",
]

CAPTURE_JSON = "capture.json"
FORMAT_VERSION = 1
IMAGE_EXTS: tuple[str, ...] = (".png", ".jpg", ".exr")
MASK_EXTS: tuple[str, ...] = (".png",)
NORMAL_EXTS: tuple[str, ...] = (".png", ".exr")

@dataclass(frozen=True)
class Problem:
    """One thing wrong with a capture or a source: the file it concerns and what is wrong."""

    path: str
    """File or folder the problem is about (relative to the capture root when inside it)."""
    message: str
    """What is wrong, phrased so the user knows what to fix."""

    def __str__(self) -> str:
        return f"{self.path}: {self.message}"


class CaptureError(ValueError):
    """A capture or an import source has problems; ``problems`` lists every one found."""

    def __init__(self, problems: list[Problem]):
        self.problems = list(problems)
        lines = "\n".join(f"  {p}" for p in self.problems)
        super().__init__(f"{len(self.problems)} problem(s):\n{lines}")


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera, OpenCV axes (x right, y down, z forward), optional OpenCV distortion.

    Pixel (u, v) has its centre at image coordinate (u + 0.5, v + 0.5); ``K`` maps to those
    continuous coordinates.
    """

    id: str
    width: int
    height: int
    K: np.ndarray
    """(3, 3) float64 intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."""
    world_to_camera: np.ndarray
    """(4, 4) float64 rigid transform from world to camera coordinates."""
    distortion: tuple[float, float, float, float, float] | None = None
    """OpenCV (k1, k2, p1, p2, k3), or None for an ideal pinhole."""

    @property
    def R(self) -> np.ndarray:
        return self.world_to_camera[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return self.world_to_camera[:3, 3]

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return -self.R.T @ self.t

    @property
    def camera_to_world(self) -> np.ndarray:
        return np.linalg.inv(self.world_to_camera)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (N, 3) to pixel coordinates (N, 2) and camera depth z (N,).

        Distortion, when present, is applied with the OpenCV model, so this is the reference the
        importers' reprojection tests compare against.
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        cam = pts @ self.R.T + self.t
        z = cam[:, 2]
        u, v = self.pixels(cam[:, 0] / z, cam[:, 1] / z)
        return np.stack([u, v], axis=1), z

    def pixels(self, x, y):
        """Pixel coordinates (u, v) of normalized camera coordinates (x, y) = (X/Z, Y/Z), with
        the distortion applied: plain arithmetic on Python floats, so numpy arrays and torch
        tensors (a GPU's, `core.mesh.build`) both go through it."""
        if self.distortion is not None:
            k1, k2, p1, p2, k3 = (float(c) for c in self.distortion)
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
            x, y = (
                x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
            )
        K = [[float(k) for k in row] for row in self.K[:2]]
        return K[0][0] * x + K[0][1] * y + K[0][2], K[1][1] * y + K[1][2]

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera seen at another resolution (intrinsics scaled per axis)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        return Camera(self.id, width, height, K, self.world_to_camera.copy(), self.distortion)

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "world_to_camera": self.world_to_camera.tolist(),
            "distortion": None if self.distortion is None else list(self.distortion),
        }


@dataclass(frozen=True)
class View:
    """The files of one camera in one frame; ``mask`` and ``normal`` are None when absent."""

    frame: str
    camera: str
    image: Path | None
    mask: Path | None
    normal: Path | None


@dataclass(eq=False)
class Capture:
    """A capture in the canonical layout rooted at ``root``."""

    root: Path
    cameras: tuple[Camera, ...]
    frames: tuple[str, ...]
    up: tuple[float, float, float]
    """World up direction (unit vector)."""
    normals_space: Literal["world", "camera"] = "world"
    import_record: dict[str, Any] | None = None
    """How an importer produced this capture, including the transform back to the source."""
    test_cameras: tuple[str, ...] | None = None
    """The cameras its dataset holds out for evaluation (capture.json `test_cameras`), or None
    when it declares none (`core.config.views`)."""
    masks: Literal["matte", "subject"] = "matte"
    """What its masks are (capture.json `masks`): `matte`, they cut the subject out of each
    picture and only it is reconstructed; `subject`, they mark the subject (the performers)
    inside a scene that is reconstructed whole (docs/capture-format.md)."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Keys of capture.json this version does not interpret, kept so saving loses nothing."""

    def camera(self, camera_id: str) -> Camera:
        for cam in self.cameras:
            if cam.id == camera_id:
                return cam
        raise KeyError(f"camera_id: no camera {camera_id!r} in {self.root / CAPTURE_JSON}")

    def image_path(self, frame: str, camera_id: str) -> Path | None:
        return _find(self.root / "images" / frame, camera_id, IMAGE_EXTS)

    def mask_path(self, frame: str, camera_id: str) -> Path | None:
        return _find(self.root / "masks" / frame, camera_id, MASK_EXTS)

    def normal_path(self, frame: str, camera_id: str) -> Path | None:
        return _find(self.root / "normals" / frame, camera_id, NORMAL_EXTS)

    def points_path(self) -> Path | None:
        """The optional ``points.ply`` that seeds training (core.data.points), or None."""
        path = self.root / POINTS_PLY
        return path if path.is_file() and not path.is_symlink() else None

    def view(self, frame: str, camera_id: str) -> View:
        return View(
            frame,
            camera_id,
            self.image_path(frame, camera_id),
            self.mask_path(frame, camera_id),
            self.normal_path(frame, camera_id),
        )

    def views(self) -> list[View]:
        """Every (frame, camera) pair, frame-major, in capture.json order."""
        return [self.view(f, c.id) for f in self.frames for c in self.cameras]

    def to_json(self) -> dict[str, Any]:
        data: dict[str, Any] = {
            "version": FORMAT_VERSION,
            "up": [float(x) for x in self.up],
            "frames": list(self.frames),
            "cameras": [c.to_json() for c in self.cameras],
        }
        if self.normals_space != "world":
            data["normals_space"] = self.normals_space
        if self.test_cameras is not None:
            data["test_cameras"] = list(self.test_cameras)
        if self.masks != "matte":
            data["masks"] = self.masks
        if self.import_record is not None:
            data["import"] = self.import_record
        data.update({k: v for k, v in self.extra.items() if k not in data})
        return data


def _find(folder: Path, stem: str, exts: tuple[str, ...]) -> Path | None:
    for ext in exts:
        path = folder / f"{stem}{ext}"
        if path.is_file():
            return path
    return None


def save_capture(capture: Capture, root: Path | None = None) -> Path:
    """Write capture.json atomically under ``root`` (default ``capture.root``); returns the path."""
    root = Path(root if root is not None else capture.root)
    path = root / CAPTURE_JSON
    write_text(path, _dumps(capture.to_json()) + "\n")
    return path


# An innermost JSON array of numbers (a matrix row, a vector); NaN/Infinity are Python's spelling.
_NUMBER_ARRAY = re.compile(
    r"\[\s*((?:-?(?:[0-9.eE+\-]+|NaN|Infinity)\s*,\s*)*-?(?:[0-9.eE+\-]+|NaN|Infinity))\s*\]"
)


def _dumps(data: dict[str, Any]) -> str:
    """Indented JSON with each vector and matrix row on one line, so capture.json stays readable."""
    text = json.dumps(data, indent=1)
    return _NUMBER_ARRAY.sub(
        lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text
    )
