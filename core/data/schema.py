"""Parsing ``capture.json`` (docs/design.md section 3.1), here and nowhere else.

Parsing collects every schema problem instead of stopping at the first, so ``dgs capture
validate`` can report them all in one pass. This module must not import torch.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from core.data.capture import (
    CAPTURE_JSON,
    FORMAT_VERSION,
    Camera,
    Capture,
    CaptureError,
    Problem,
    valid_name,
)
from core.data.rules import json_values_problem, read_bounded

__all__ = [
    "extrinsics_problems",
    "intrinsics_problems",
    "load_capture",
    "parse_camera",
    "parse_capture_json",
    "read_json",
]

_ROTATION_TOL = 1e-4


def read_json(path: Path) -> Any:
    """The JSON document in ``path``; ValueError saying what is wrong (never naming the path:
    callers name the file) when it is larger or holds more values than a metadata file may
    (core.data.rules, checked before it is parsed), cannot be read, is not UTF-8, not JSON,
    or nested too deeply for the parser."""
    data = read_bounded(Path(path))
    problem = json_values_problem(data)
    if problem is not None:
        raise ValueError(problem)
    try:
        return json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot parse JSON: {exc}") from None
    except RecursionError:
        raise ValueError("cannot parse JSON: nested too deeply") from None
    except ValueError as exc:  # an integer of more digits than Python converts
        raise ValueError(f"cannot parse JSON: {exc}") from None


def load_capture(root: str | os.PathLike[str]) -> Capture:
    """Read ``root/capture.json``; raises :class:`CaptureError` listing every schema problem."""
    root = Path(root)
    path = root / CAPTURE_JSON
    if not path.is_file():
        raise CaptureError(
            [Problem(str(path), "capture.json not found (is this a capture folder?)")]
        )
    try:
        data = read_json(path)
    except ValueError as exc:
        raise CaptureError([Problem(str(path), f"capture.json: {exc}")]) from None
    capture, problems = parse_capture_json(data, root)
    if problems or capture is None:
        raise CaptureError(problems)
    return capture


def parse_capture_json(data: Any, root: Path) -> tuple[Capture | None, list[Problem]]:
    """Parse a decoded capture.json; returns the capture and all problems.

    With problems the capture is partial (cameras with bad entries are left out) or None when
    nothing usable remains; callers that need a sound capture must check ``problems``.
    """
    where = CAPTURE_JSON
    if not isinstance(data, dict):
        return None, [Problem(where, "top level must be a JSON object")]
    problems: list[Problem] = []
    if data.get("version") != FORMAT_VERSION:
        problems.append(
            Problem(where, f"version must be {FORMAT_VERSION}, got {data.get('version')!r}")
        )
    up = _parse_up(data.get("up"), problems)
    frames = _parse_frames(data.get("frames"), problems)
    cameras = _parse_cameras(data.get("cameras"), problems)
    space = data.get("normals_space", "world")
    if space not in ("world", "camera"):
        problems.append(Problem(where, f"normals_space must be 'world' or 'camera', got {space!r}"))
    known = {"version", "up", "frames", "cameras", "normals_space", "import", "test_cameras",
             "masks"}
    extra = {k: v for k, v in data.items() if k not in known}
    record = data.get("import")
    test = _parse_test_cameras(data.get("test_cameras"), cameras, problems)
    masks = data.get("masks", "matte")
    if masks not in ("matte", "subject"):
        problems.append(Problem(where, f"masks must be 'matte' or 'subject', got "
                                f"{json.dumps(masks)[:40]}"))
        masks = "matte"
    if not frames or not isinstance(data.get("cameras"), list):
        return None, problems
    # Returned even with problems (bad cameras left out) so validation can go on to the files.
    valid_space = space if space in ("world", "camera") else "world"
    return Capture(root, tuple(cameras), tuple(frames), up, valid_space, record, test, masks,
                   extra), problems


def _parse_test_cameras(value: Any, cameras: list[Camera],
                        problems: list[Problem]) -> tuple[str, ...] | None:
    """capture.json `test_cameras`: absent/null, or a list of distinct ids of its cameras that
    leaves at least one camera to train on."""
    if value is None:
        return None
    ids = {c.id for c in cameras}
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        problems.append(Problem(CAPTURE_JSON, "test_cameras must be null or a list of camera "
                                f"ids, got {json.dumps(value)[:80]}"))
        return None
    bad = [v for v in value if v not in ids]
    if bad and cameras:
        shown = ", ".join(repr(b)[:40] for b in bad[:5])
        problems.append(Problem(CAPTURE_JSON, f"test_cameras: {shown} not among the cameras"))
    if len(set(value)) != len(value):
        problems.append(Problem(CAPTURE_JSON, "test_cameras: an id is listed twice"))
    if cameras and set(value) >= ids:
        problems.append(Problem(CAPTURE_JSON, "test_cameras: every camera is held out; leave "
                                "at least one to train on"))
    return tuple(v for v in value if v in ids)


def _parse_up(value: Any, problems: list[Problem]) -> tuple[float, float, float]:
    vec = _float_array(value, (3,))
    if vec is None or np.linalg.norm(vec) < 1e-9:
        problems.append(Problem(CAPTURE_JSON, f"up must be a non-zero 3-vector, got {value!r}"))
        return (0.0, 0.0, 1.0)
    vec = vec / np.linalg.norm(vec)
    return (float(vec[0]), float(vec[1]), float(vec[2]))


def _parse_frames(value: Any, problems: list[Problem]) -> list[str]:
    if not isinstance(value, list) or not value:
        problems.append(Problem(CAPTURE_JSON, "frames must be a non-empty list of names"))
        return []
    seen: set[str] = set()
    for name in value:
        if not valid_name(name):
            problems.append(
                Problem(
                    CAPTURE_JSON, f"frame name {name!r} is not a safe file name ([A-Za-z0-9_.-])"
                )
            )
        elif name in seen:
            problems.append(Problem(CAPTURE_JSON, f"duplicate frame {name!r}"))
        else:
            seen.add(name)
    return [n for n in value if valid_name(n)]  # never let an unsafe name reach the file system


def _parse_cameras(value: Any, problems: list[Problem]) -> list[Camera]:
    if not isinstance(value, list) or not value:
        problems.append(Problem(CAPTURE_JSON, "cameras must be a non-empty list"))
        return []
    cameras: list[Camera] = []
    seen: set[str] = set()
    for i, entry in enumerate(value):
        cam = parse_camera(entry, f"{CAPTURE_JSON} cameras[{i}]", problems)
        if cam is None:
            continue
        if cam.id in seen:
            problems.append(Problem(CAPTURE_JSON, f"duplicate camera id {cam.id!r} (cameras[{i}])"))
        seen.add(cam.id)
        cameras.append(cam)
    return cameras


def parse_camera(entry: Any, where: str, problems: list[Problem]) -> Camera | None:
    """One camera entry of capture.json; appends problems naming ``where``, None if bad."""
    if not isinstance(entry, dict):
        problems.append(Problem(CAPTURE_JSON, f"{where}: must be an object"))
        return None
    n_before = len(problems)
    cid = entry.get("id")
    if not valid_name(cid):
        problems.append(Problem(CAPTURE_JSON, f"{where}: id {cid!r} is not a safe file name"))
    label = f"{where} ({cid})" if isinstance(cid, str) else where
    width, height = entry.get("width"), entry.get("height")
    for key, val in (("width", width), ("height", height)):
        if not isinstance(val, int) or isinstance(val, bool) or val <= 0:
            problems.append(
                Problem(CAPTURE_JSON, f"{label}: {key} must be a positive integer, got {val!r}")
            )
    K = _float_array(entry.get("K"), (3, 3))
    problems.extend(Problem(CAPTURE_JSON, f"{label}: {m}") for m in intrinsics_problems(K))
    w2c = _float_array(entry.get("world_to_camera"), (4, 4))
    problems.extend(Problem(CAPTURE_JSON, f"{label}: {m}") for m in extrinsics_problems(w2c))
    dist = entry.get("distortion")
    dist_t = None
    if dist is not None:
        arr = _float_array(dist, (len(dist),)) if isinstance(dist, list) else None
        if arr is None or len(arr) not in (4, 5) or not np.all(np.isfinite(arr)):
            problems.append(
                Problem(
                    CAPTURE_JSON,
                    f"{label}: distortion must be null or 4-5 finite numbers, got {dist!r}",
                )
            )
        else:
            vals = [float(x) for x in arr] + [0.0] * (5 - len(arr))
            dist_t = tuple(vals) if any(vals) else None
    if len(problems) > n_before:
        return None
    return Camera(cid, width, height, K, w2c, dist_t)  # type: ignore[arg-type]


def intrinsics_problems(K: np.ndarray | None) -> list[str]:
    """Why ``K`` is not a usable pinhole matrix (empty when it is)."""
    if K is None:
        return ["K must be a 3x3 matrix of numbers"]
    if not np.all(np.isfinite(K)):
        return [f"K has non-finite entries: {K.tolist()}"]
    out = []
    if K[0, 0] <= 1e-6 or K[1, 1] <= 1e-6:
        out.append(f"K has degenerate focal lengths fx={K[0, 0]}, fy={K[1, 1]} (must be > 0)")
    if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        out.append(f"K must have the form [[fx,0,cx],[0,fy,cy],[0,0,1]], got {K.tolist()}")
    return out


def extrinsics_problems(w2c: np.ndarray | None, name: str = "world_to_camera",
                        *, proper: bool = True) -> list[str]:
    """Why ``w2c`` (called `name` in the messages) is not a rigid transform (empty when it
    is). ``proper=False`` lets a reflection (det -1) through: the importers read a mirrored
    world as it is and settle it for the whole rig (`core.data.importers.rig`)."""
    if w2c is None:
        return [f"{name} must be a 4x4 matrix of numbers"]
    if not np.all(np.isfinite(w2c)):
        return [f"{name} has non-finite entries"]
    out = []
    if np.abs(w2c[3] - np.array([0, 0, 0, 1.0])).max() > 1e-9:
        out.append(f"{name} last row must be [0,0,0,1], got {w2c[3].tolist()}")
    R = w2c[:3, :3]
    with np.errstate(all="ignore"):  # huge entries overflow to inf: not a rotation either
        err = float(np.abs(R @ R.T - np.eye(3)).max())
        det = float(np.linalg.det(R))
    if not err <= _ROTATION_TOL or not (det > 0 or not proper and det < 0):
        out.append(
            f"{name} rotation is not a rotation (|R R^T - I| = {err:.2e}, det = "
            f"{det:.4f}); expected orthonormal with det {'+1' if proper else '+1 or -1'}"
        )
    return out


def _float_array(value: Any, shape: tuple[int, ...]) -> np.ndarray | None:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):  # not numbers, ragged, or past float64
        return None
    if arr.shape != shape:
        return None
    return arr
