"""Which cameras a relight renders: the capture's (held-out, all, or listed ids), an orbit around
the subject, or a nerfstudio camera_path.json.

nerfstudio's camera_path.json (viewer export, cameras/camera_paths.py `get_path_from_json`):
top-level `render_width`, `render_height`, `camera_path` = [{`camera_to_world`: 16 numbers,
row-major 4x4, OpenGL camera axes (x right, y up, looking down -z), `fov`: vertical field of
view in degrees, `aspect`: width / height}, ...], optional `fps`. The image is `render_height`
high and `aspect * render_height` wide (nerfstudio's rule), the focal length
`height / (2 tan(fov / 2))` (three.js PerspectiveCamera). Poses are read in the capture's world
coordinates (the frame an import keeps; `dgs capture import` leaves the source world as is).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from core.data.capture import Camera
from core.config import Views
from core.relight.envmap import up_frame
from core.synth.generate import look_at

__all__ = ["load_camera_path", "orbit_cameras", "select_cameras"]

# OpenGL camera axes (y up, looking down -z) to OpenCV (y down, z forward).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def select_cameras(capture, spec: str, views: Views) -> list[Camera]:
    """Cameras of a `core.data.Capture`: `heldout` (those the run's `views` score: its
    held-out cameras, or its training ones when it held none out), `all`, or comma-separated
    camera ids."""
    cameras = capture.cameras
    spec = (spec or "").strip()
    if spec == "heldout":
        return views.cameras(capture, "scored")
    if spec == "all":
        return list(cameras)
    ids = [s.strip() for s in spec.split(",") if s.strip()]
    if not ids:
        raise ValueError(f"cameras: expected heldout, all or camera ids ID,ID, got {spec!r}")
    known = {c.id: c for c in cameras}
    missing = [i for i in ids if i not in known]
    if missing:
        shown = ", ".join(list(known)[:8]) + (" ..." if len(known) > 8 else "")
        raise ValueError(f"cameras: no camera {', '.join(missing)} in the capture (it has "
                         f"{shown})")
    return [known[i] for i in ids]


def _look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    return look_at(eye, target, up)


def orbit_cameras(cameras: Sequence[Camera], center: np.ndarray, up, n: int) -> list[Camera]:
    """`n` cameras evenly spaced in azimuth about `up` through `center`, at the cameras' mean
    distance and mean elevation, starting at the first camera's azimuth, with its intrinsics and
    size; ids orbit000, orbit001, ..."""
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"orbit: expected a number of views >= 1, got {n!r}")
    if not cameras:
        raise ValueError("orbit: the capture has no camera to take the distance and lens from")

    e1, e2, u = up_frame(up)
    offsets = np.stack([c.center for c in cameras]) - center
    dist = float(np.linalg.norm(offsets, axis=1).mean())
    elev = float(np.mean(np.arcsin(np.clip(offsets @ u / np.linalg.norm(offsets, axis=1),
                                           -1, 1))))
    az0 = math.atan2(offsets[0] @ e2, offsets[0] @ e1)
    ref, digits = cameras[0], max(3, len(str(n - 1)))
    out = []
    for i in range(n):
        az = az0 + 2 * math.pi * i / n
        direction = math.cos(elev) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(elev) * u
        eye = center + dist * direction
        out.append(Camera(f"orbit{i:0{digits}d}", ref.width, ref.height, ref.K.copy(),
                          _look_at(eye, center, u), None))
    return out


def _number(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{where}: expected a finite number, got {value!r}")
    return float(value)


def load_camera_path(path) -> tuple[list[Camera], float | None]:
    """Cameras (ids path000, ...) of a nerfstudio camera_path.json and its fps (None if absent);
    ValueError naming the file and the entry for anything malformed."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"camera_path: cannot read {path}: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("camera_path"), list):
        raise ValueError(f"camera_path: {path} has no 'camera_path' list (expected nerfstudio's "
                         "camera_path.json)")
    if not doc["camera_path"]:
        raise ValueError(f"camera_path: {path} has an empty 'camera_path' (no view to render)")
    height = int(_number(doc.get("render_height"), f"{path}: render_height"))
    if height < 2:
        raise ValueError(f"camera_path: {path}: render_height must be >= 2, got {height}")
    default_aspect = _number(doc.get("render_width", height), f"{path}: render_width") / height
    cams = []
    digits = max(3, len(str(len(doc["camera_path"]) - 1)))
    for i, entry in enumerate(doc["camera_path"]):
        where = f"{path}: camera_path[{i}]"
        if not isinstance(entry, dict):
            raise ValueError(f"{where}: expected an object, got {entry!r}")
        m = np.asarray(entry.get("camera_to_world"), dtype=object)
        if m.size != 16 or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                   for x in m.ravel()):
            raise ValueError(f"{where}: camera_to_world must be 16 numbers (row-major 4x4)")
        c2w = np.asarray(m.ravel(), dtype=np.float64).reshape(4, 4)
        if not np.isfinite(c2w).all() or abs(np.linalg.det(c2w[:3, :3])) < 1e-9:
            raise ValueError(f"{where}: camera_to_world is not a finite, invertible pose")
        fov = _number(entry.get("fov"), f"{where}: fov")
        if not 0 < fov < 180:
            raise ValueError(f"{where}: fov must be in (0, 180) degrees, got {fov}")
        aspect = _number(entry.get("aspect", default_aspect), f"{where}: aspect")
        width = max(2, int(round(aspect * height)))
        f = height / (2 * math.tan(math.radians(fov) / 2))
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
        w2c = np.linalg.inv(c2w @ _GL_TO_CV)
        cams.append(Camera(f"path{i:0{digits}d}", width, height, K, w2c, None))
    fps = doc.get("fps")
    return cams, (_number(fps, f"{path}: fps") if fps is not None else None)
