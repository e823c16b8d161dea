"""CMU Panoptic Studio sequences as Dynamic 3D Gaussians prepares them (Luiten et al., 3DV 2024):
reader and writer.

The layout: ``train_meta.json`` and ``test_meta.json`` (the dataset's split), each with ``w``,
``h`` and, per frame t, lists over that split's cameras: ``k[t][i]`` (3x3 intrinsics),
``w2c[t][i]`` (4x4 world-to-camera, OpenCV axes), ``fn[t][i]`` (the image, ``<cam>/<frame>.jpg``
under ``ims/``) and ``cam_id[t][i]``. Foreground masks ``seg/<cam>/<frame>.png`` (any non-zero
pixel is the subject) exist for the training cameras; ``init_pt_cld.npz`` (``data``: x, y, z,
r, g, b, seg per row), when present, becomes points.ply.

The calibration is given per frame, but a capture has one rig: every frame's ``k`` and ``w2c``
of a camera must equal the first frame's, or the import is refused naming the frame and camera
that differ. Pixel centres sit at integer coordinates in this calibration (OpenCV's, and the
3DGS rasterizer the dataset was made for), so 0.5 is added to cx and cy. The test cameras
become capture.json ``test_cameras``. The masks mark the players and the ball in a scene
whose dome is reconstructed too: capture.json says ``"masks": "subject"`` (docs/capture-format.md).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from core.data.capture import Camera, Capture, CaptureError, Problem
from core.data.importers.common import ImportedCapture, SourceView, safe_name, source_transform
from core.data.points import PointCloud
from core.data.schema import extrinsics_problems, intrinsics_problems

__all__ = ["CALIBRATION_TOLERANCE", "export_panoptic", "find_meta", "read_panoptic"]

_TRAIN, _TEST = "train_meta.json", "test_meta.json"
_KEYS = ("w", "h", "k", "w2c", "fn", "cam_id")
CALIBRATION_TOLERANCE = 1e-6
"""Largest difference (relative to the value's scale) between two frames' calibration of one
camera that still counts as the same rig (the dataset repeats it to the last digit)."""


def find_meta(src: Path) -> Path | None:
    """``train_meta.json`` of a Panoptic folder (or the file itself), or None."""
    src = Path(src)
    if src.is_file():
        return src if src.name == _TRAIN else None
    path = src / _TRAIN
    return path if path.is_file() else None


def _load_meta(path: Path, problems: list[Problem]) -> dict | None:
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        problems.append(Problem(str(path), f"cannot read JSON: {exc}"))
        return None
    missing = [k for k in _KEYS if not isinstance(meta, dict) or k not in meta]
    if missing:
        problems.append(Problem(str(path), f"expected keys {', '.join(_KEYS)}; missing "
                                f"{', '.join(missing)}"))
        return None
    lengths = {k: len(meta[k]) if isinstance(meta[k], list) else -1 for k in _KEYS[2:]}
    if min(lengths.values()) < 1 or len(set(lengths.values())) != 1:
        problems.append(Problem(str(path), "k, w2c, fn and cam_id must be lists with one entry "
                                f"per frame, got lengths {lengths}"))
        return None
    return meta


def _frame_of(fn: str) -> tuple[str, str]:
    """(camera folder, frame name) of a ``<cam>/<frame>.jpg`` entry."""
    cam, _, name = str(fn).replace("\\", "/").rpartition("/")
    return cam, name.rsplit(".", 1)[0]


def _rig(meta: dict, path: Path, problems: list[Problem]) -> dict[str, tuple]:
    """{camera folder: (K, w2c, cam id)} of the first frame, every later frame checked
    against it (one rig), and the frame names per camera checked to agree."""
    rig: dict[str, tuple] = {}
    frames = len(meta["fn"])
    for t in range(frames):
        ids, ks, w2cs, fns = (meta[k][t] for k in ("cam_id", "k", "w2c", "fn"))
        if not (len(ids) == len(ks) == len(w2cs) == len(fns)):
            problems.append(Problem(str(path), f"frame {t}: cam_id, k, w2c and fn differ in "
                                    "length"))
            return {}
        for cid, k, w2c, fn in zip(ids, ks, w2cs, fns):
            folder, _ = _frame_of(fn)
            try:
                K, E = np.asarray(k, np.float64), np.asarray(w2c, np.float64)
            except (TypeError, ValueError):
                problems.append(Problem(str(path), f"frame {t}, camera {cid}: k or w2c is not "
                                        "a matrix of numbers"))
                return {}
            if t == 0:
                rig[folder] = (K, E, cid)
                continue
            first = rig.get(folder)
            if first is None:
                problems.append(Problem(str(path), f"frame {t}: camera {cid} is not in frame 0"))
                return {}
            if K.shape != first[0].shape or E.shape != first[1].shape or not (
                    _same(K, first[0]) and _same(E, first[1])):
                what = "k" if K.shape != first[0].shape or not _same(K, first[0]) else "w2c"
                problems.append(Problem(str(path), f"frame {t} ({_frame_of(fn)[1]}), camera "
                                        f"{cid}: {what} differs from frame 0; a capture has "
                                        "one rig (calibration that moves between frames is "
                                        "not supported)"))
                return {}
        if t > 0 and len(ids) != len(rig):
            problems.append(Problem(str(path), f"frame {t}: {len(ids)} cameras, frame 0 has "
                                    f"{len(rig)}"))
            return {}
    return rig


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    scale = max(1.0, float(np.abs(b).max()))
    return bool(np.all(np.isfinite(a))) and float(np.abs(a - b).max()) <= \
        CALIBRATION_TOLERANCE * scale


def _camera(folder: str, K: np.ndarray, w2c: np.ndarray, w: int, h: int, where: str,
            problems: list[Problem]) -> Camera | None:
    K = K.copy()
    if K.shape == (3, 3):
        K[0, 2] += 0.5  # integer pixel centres in the source
        K[1, 2] += 0.5
    bad = intrinsics_problems(K if K.shape == (3, 3) else None) + extrinsics_problems(
        w2c if w2c.shape == (4, 4) else None)
    problems.extend(Problem(where, m) for m in bad)
    return None if bad else Camera(safe_name(folder), w, h, K, w2c, None)


def _size(meta: dict, path: Path, problems: list[Problem]) -> tuple[int, int]:
    w, h = meta["w"], meta["h"]
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (w, h)):
        problems.append(Problem(str(path), f"w and h must be positive integers, got {w!r}, "
                                f"{h!r}"))
        return 0, 0
    return w, h


def _points(root: Path, problems: list[Problem]) -> PointCloud | None:
    path = root / "init_pt_cld.npz"
    if not path.is_file():
        return None
    try:
        data = np.load(path)["data"]
        xyz, rgb = np.asarray(data[:, :3], np.float64), np.asarray(data[:, 3:6], np.float64)
    except (OSError, KeyError, ValueError, IndexError) as exc:
        problems.append(Problem(str(path), f"cannot read the point cloud ('data': N x 7): "
                                f"{exc}"))
        return None
    keep = np.all(np.isfinite(xyz), axis=1)
    return PointCloud(xyz[keep], np.clip(rgb[keep], 0, 1))


def read_panoptic(src: str | Path) -> ImportedCapture:
    """Read a Panoptic / Dynamic 3D Gaussians folder; CaptureError listing every problem."""
    train_path = find_meta(Path(src))
    if train_path is None:
        raise CaptureError([Problem(str(src), f"{_TRAIN} not found")])
    root = train_path.parent
    problems: list[Problem] = []
    metas = [(train_path, _load_meta(train_path, problems))]
    if (root / _TEST).is_file():
        metas.append((root / _TEST, _load_meta(root / _TEST, problems)))
    if problems:
        raise CaptureError(problems)
    cameras: dict[str, Camera] = {}
    frames: list[str] | None = None
    test: list[str] = []
    images: dict[tuple[str, str], Path] = {}
    for path, meta in metas:
        w, h = _size(meta, path, problems)
        rig = _rig(meta, path, problems)
        these = [_frame_of(meta["fn"][t][0])[1] for t in range(len(meta["fn"]))]
        for t, frame in enumerate(these):
            for fn in meta["fn"][t]:
                images[(frame, _frame_of(fn)[0])] = root / "ims" / str(fn)
        if frames is None:
            frames = these
        elif these != frames:
            problems.append(Problem(str(path), f"its {len(these)} frames differ from "
                                    f"{_TRAIN}'s {len(frames)}"))
        for folder, (K, E, cid) in rig.items():
            cam = _camera(folder, K, E, w, h, f"{path} camera {cid}", problems)
            if cam is None:
                continue
            if cam.id in cameras:
                problems.append(Problem(str(path), f"camera {cid} appears in both splits"))
            cameras[cam.id] = cam
            if path.name == _TEST:
                test.append(cam.id)
    points = _points(root, problems)
    if problems:
        raise CaptureError(problems)
    order = sorted(cameras, key=lambda c: (len(c), c))  # numeric folder names in order
    views = []
    for frame in frames or []:
        for cid in order:
            mask = root / "seg" / cid / f"{frame}.png"
            views.append(SourceView(safe_name(frame), cid, images[(frame, cid)],
                                    mask if mask.is_file() else None))
    cams = [cameras[c] for c in order]
    record: dict[str, Any] = {
        "format": "panoptic",
        "source": str(root.resolve()),
        "to_source": source_transform(np.eye(4), "w2c = world_to_camera; k = K - 0.5 on cx, "
                                      "cy (integer pixel centres)"),
    }
    ups = np.stack([-c.R[1] for c in cams]).mean(axis=0)  # the cameras' mean up (-y)
    up = ups / max(float(np.linalg.norm(ups)), 1e-12)
    files = [p for p, _ in metas]
    return ImportedCapture(cams, [safe_name(f) for f in frames or []],
                           (float(up[0]), float(up[1]), float(up[2])), views, record, files,
                           points, test_cameras=test or None, masks="subject")


def export_panoptic(capture: Capture, dst: str | Path, test_cameras: list[str] | None = None
                    ) -> Path:
    """Write `capture` in this layout (``ims/``, ``seg/``, ``train_meta.json``, and
    ``test_meta.json`` for `test_cameras`, default the capture's); returns train_meta.json.
    Camera ids must be folder names; distortion is refused (the layout has none)."""
    dst = Path(dst)
    test = set(test_cameras if test_cameras is not None else capture.test_cameras or ())
    for split, cams in ((_TRAIN, [c for c in capture.cameras if c.id not in test]),
                        (_TEST, [c for c in capture.cameras if c.id in test])):
        if not cams:
            continue
        if any(c.distortion is not None for c in cams):
            raise ValueError("capture: a camera has distortion, which this layout cannot hold")
        meta: dict[str, Any] = {"w": cams[0].width, "h": cams[0].height, "k": [], "w2c": [],
                                "fn": [], "cam_id": []}
        for frame in capture.frames:
            ks = []
            for c in cams:
                K = c.K.copy()
                K[0, 2] -= 0.5
                K[1, 2] -= 0.5
                ks.append(K.tolist())
            meta["k"].append(ks)
            meta["w2c"].append([c.world_to_camera.tolist() for c in cams])
            meta["cam_id"].append([int(c.id) if c.id.isdigit() else c.id for c in cams])
            names = []
            for c in cams:
                src = capture.image_path(frame, c.id)
                if src is None:
                    raise FileNotFoundError(f"images/{frame}/{c.id}.*: missing image")
                names.append(f"{c.id}/{frame}{src.suffix}")
                out = dst / "ims" / names[-1]
                out.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src, out)
                mask = capture.mask_path(frame, c.id)
                if mask is not None and split == _TRAIN:
                    out = dst / "seg" / c.id / f"{frame}.png"
                    out.parent.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(mask, out)
            meta["fn"].append(names)
        (dst / split).write_text(json.dumps(meta))
    return dst / _TRAIN
