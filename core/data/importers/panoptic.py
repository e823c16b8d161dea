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
import os
import shutil
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import AfterValidator
from pydantic_core import PydanticCustomError

from core.data.capture import Camera, Capture, CaptureError, Problem
from core.data.importers.common import (
    ImportedCapture,
    PoseSource,
    SourceView,
    safe_name,
    source_transform,
)
from core.data.importers.records import (
    MAX_CAMERAS,
    MAX_FRAMES,
    IdOrNumber,
    Record,
    Side,
    SourcePath,
    listof,
    load_json,
    load_npz,
    matrix,
    stem,
)
from core.data.points import PointCloud
from core.data.rules import name_problem
from core.data.schema import extrinsics_problems, intrinsics_problems

__all__ = ["CALIBRATION_TOLERANCE", "export_panoptic", "find_meta", "read_panoptic"]

_TRAIN, _TEST = "train_meta.json", "test_meta.json"
CALIBRATION_TOLERANCE = 1e-6
"""Largest difference (relative to the value's scale) between two frames' calibration of one
camera that still counts as the same rig (the dataset repeats it to the last digit)."""


def _fn(value: str) -> str:
    parts = value.split("/")
    if len(parts) != 2:
        raise PydanticCustomError("source_path", "{fn} must be <camera folder>/<frame>.<ext>",
                                  {"fn": repr(value)[:80]})
    for what, name in (("camera folder", parts[0]), ("frame", stem(parts[1]))):
        problem = name_problem(name)
        if problem is not None:
            raise PydanticCustomError("source_name", "{what} {name}: {problem}",
                                      {"what": what, "name": repr(name)[:80], "problem": problem})
    return value


def _per_frame(item: Any) -> Any:
    return listof(listof(item, MAX_CAMERAS), MAX_FRAMES)


Fn = Annotated[SourcePath, AfterValidator(_fn)]
_Ks, _W2Cs = _per_frame(matrix(3, 3)), _per_frame(matrix(4, 4))
_Fns, _Ids = _per_frame(Fn), _per_frame(IdOrNumber)


class PanopticMeta(Record):
    """train_meta.json / test_meta.json: per frame t, lists over the split's cameras."""

    w: Side
    h: Side
    k: _Ks
    """k[t][i]: 3x3 intrinsics, integer pixel centres."""
    w2c: _W2Cs
    """w2c[t][i]: 4x4 world-to-camera, OpenCV axes."""
    fn: _Fns
    """fn[t][i]: the image, ``<camera folder>/<frame>.<ext>`` under ``ims/``."""
    cam_id: _Ids
    """cam_id[t][i]: the dataset's camera number (used in messages)."""


def find_meta(src: Path) -> Path | None:
    """``train_meta.json`` of a Panoptic folder (or the file itself), or None."""
    src = Path(src)
    if src.is_file():
        return src if src.name == _TRAIN else None
    path = src / _TRAIN
    return path if path.is_file() else None


def _shape_problems(meta: PanopticMeta, path: Path) -> list[Problem]:
    lengths = {k: len(getattr(meta, k)) for k in ("k", "w2c", "fn", "cam_id")}
    if len(set(lengths.values())) != 1:
        return [Problem(str(path), f"k, w2c, fn and cam_id must have one entry per frame, got "
                                   f"lengths {lengths}")]
    for t in range(lengths["fn"]):
        per = {k: len(getattr(meta, k)[t]) for k in lengths}
        if len(set(per.values())) != 1:
            return [Problem(str(path), f"frame {t}: cam_id[{t}], k[{t}], w2c[{t}] and fn[{t}] "
                                       f"must list the same cameras, got lengths {per}")]
    return []


def _frames(meta: PanopticMeta, path: Path, problems: list[Problem]) -> list[str]:
    """The frame name of each t, every entry of a frame naming it, each camera folder once a
    frame and every frame the cameras of frame 0."""
    names: dict[str, int] = {}  # frame name -> t (a dict: a list's `in` is quadratic)
    rig = {fn.split("/")[0] for fn in meta.fn[0]}
    for t, fns in enumerate(meta.fn):
        folders = [fn.split("/")[0] for fn in fns]
        frame = stem(fns[0].split("/")[1])
        for i, fn in enumerate(fns):
            if stem(fn.split("/")[1]) != frame:
                problems.append(Problem(str(path), f"fn[{t}][{i}]: {fn!r} names another frame "
                                        f"than fn[{t}][0] ({frame!r}); a frame's entries name "
                                        "one frame"))
                return []
        if len(set(folders)) != len(folders):
            twice = next(f for f in folders if folders.count(f) > 1)
            problems.append(Problem(str(path), f"fn[{t}]: camera folder {twice!r} appears "
                                    "twice in one frame"))
            return []
        if set(folders) != rig:
            problems.append(Problem(str(path), f"fn[{t}]: frame {t} has cameras "
                                    f"{sorted(set(folders) ^ rig)[:5]} that frame 0 has "
                                    "not, or lacks some of its cameras; a capture has one rig"))
            return []
        if frame in names:
            problems.append(Problem(str(path), f"fn[{t}]: frame {frame!r} is also frame "
                                    f"{names[frame]}"))
            return []
        names[frame] = t
    return list(names)


def _rig(meta: PanopticMeta, path: Path, problems: list[Problem]) -> dict[str, tuple]:
    """{camera folder: (K, w2c, cam id)} of frame 0, every later frame checked against it (one
    rig), all frames at once (a source may have tens of thousands)."""
    first = {fn.split("/")[0]: i for i, fn in enumerate(meta.fn[0])}
    # order[t, i]: which of frame 0's entries is the camera of entry i of frame t
    order = np.array([[first[fn.split("/")[0]] for fn in fns] for fns in meta.fn])
    for what in ("k", "w2c"):
        arr = np.asarray(getattr(meta, what), np.float64)  # (frames, cameras, rows, cols)
        ref = arr[0][order]
        with np.errstate(all="ignore"):  # huge entries overflow: they differ, then
            scale = np.maximum(1.0, np.abs(ref).max(axis=(2, 3)))
            same = np.abs(arr - ref).max(axis=(2, 3)) <= CALIBRATION_TOLERANCE * scale
        if not same.all():
            t, i = (int(x) for x in np.argwhere(~same)[0])
            problems.append(Problem(str(path), f"{what}[{t}][{i}]: frame {t} "
                                    f"({stem(meta.fn[t][i])}), camera {meta.cam_id[t][i]}: "
                                    f"{what} differs from frame 0; a capture has one rig "
                                    "(calibration that moves between frames is not "
                                    "supported)"))
            return {}
    return {folder: (np.asarray(meta.k[0][i], np.float64), np.asarray(meta.w2c[0][i],
                                                                         np.float64),
                     meta.cam_id[0][i]) for folder, i in first.items()}


def _camera(folder: str, K: np.ndarray, w2c: np.ndarray, w: int, h: int, where: str,
            problems: list[Problem]) -> Camera | None:
    K = K.copy()
    K[0, 2] += 0.5  # integer pixel centres in the source
    K[1, 2] += 0.5
    # A mirrored world (det -1) passes here; the rig checks settle it for every camera.
    bad = intrinsics_problems(K) + extrinsics_problems(w2c, proper=False)
    problems.extend(Problem(where, m) for m in bad)
    return None if bad else Camera(safe_name(folder), w, h, K, w2c, None)


def _points(root: Path, problems: list[Problem]) -> PointCloud | None:
    path = root / "init_pt_cld.npz"
    if not path.is_file():
        return None
    try:
        data = load_npz(path, limit=1 << 31)
    except CaptureError as exc:
        problems.extend(exc.problems)
        return None
    cloud = data.get("data")
    if cloud is None or cloud.ndim != 2 or cloud.shape[1] < 6:
        problems.append(Problem(str(path), "cannot read the point cloud: 'data' must be an "
                                "N x 7 array (x, y, z, r, g, b, seg)"))
        return None
    xyz, rgb = cloud[:, :3].astype(np.float64), cloud[:, 3:6].astype(np.float64)
    keep = np.all(np.isfinite(xyz), axis=1) & np.all(np.isfinite(rgb), axis=1)
    return PointCloud(xyz[keep], np.clip(rgb[keep], 0, 1))


def _split(path: Path, meta: PanopticMeta, problems: list[Problem]
           ) -> tuple[list[str], dict[str, Camera], dict[tuple[str, str], str]]:
    """One split's frame names, cameras by id and image paths by (frame, id)."""
    n = len(problems)
    problems.extend(_shape_problems(meta, path))
    frames = _frames(meta, path, problems) if len(problems) == n else []
    rig = _rig(meta, path, problems) if len(problems) == n else {}
    cameras: dict[str, Camera] = {}
    for folder, (K, E, cid) in rig.items():
        cam = _camera(folder, K, E, meta.w, meta.h, f"{path} camera {cid}", problems)
        if cam is not None and cam.id in cameras:
            problems.append(Problem(str(path), f"camera folders {folder!r} and another give "
                                    f"one id {cam.id!r}; rename one"))
        elif cam is not None:
            cameras[cam.id] = cam
    images = {(frame, safe_name(fn.split("/")[0])): fn
              for frame, fns in zip(frames, meta.fn) for fn in fns}
    return frames, cameras, images


def read_panoptic(src: str | Path) -> ImportedCapture:
    """Read a Panoptic / Dynamic 3D Gaussians folder; CaptureError listing every problem."""
    train_path = find_meta(Path(src))
    if train_path is None:
        raise CaptureError([Problem(str(src), f"{_TRAIN} not found")])
    root = train_path.parent
    problems: list[Problem] = []
    paths = [train_path] + ([root / _TEST] if (root / _TEST).is_file() else [])
    metas = []
    for path in paths:
        try:
            metas.append((path, load_json(path, PanopticMeta)))
        except CaptureError as exc:
            problems.extend(exc.problems)
    if problems:
        raise CaptureError(problems)
    cameras: dict[str, Camera] = {}
    frames: list[str] | None = None
    test: list[str] = []
    images: dict[tuple[str, str], Path] = {}
    for path, meta in metas:
        these, cams, files = _split(path, meta, problems)
        images.update({key: root / "ims" / fn for key, fn in files.items()})
        if frames is None:
            frames = these
        elif these != frames and not problems:
            problems.append(Problem(str(path), f"its {len(these)} frames differ from "
                                    f"{_TRAIN}'s {len(frames)}"))
        for cid, cam in cams.items():
            if cid in cameras:
                problems.append(Problem(str(path), f"camera {cid!r} appears in both splits"))
            cameras[cid] = cam
            if path.name == _TEST:
                test.append(cid)
    points = _points(root, problems)
    if problems:
        raise CaptureError(problems)
    return _imported(root, cameras, frames or [], images, test, points,
                     [p for p, _ in metas])


def _imported(root: Path, cameras: dict[str, Camera], frames: list[str],
              images: dict[tuple[str, str], Path], test: list[str], points: PointCloud | None,
              files: list[Path]) -> ImportedCapture:
    order = sorted(cameras, key=lambda c: (len(c), c))  # numeric folder names in order
    seg = {cid: root / "seg" / images[(frames[0], cid)].parent.name for cid in order}
    masks = {cid: set(os.listdir(folder)) if folder.is_dir() else set()  # one listing a camera
             for cid, folder in seg.items()}
    views = []
    for frame in frames:
        for cid in order:
            mask = seg[cid] / f"{frame}.png" if f"{frame}.png" in masks[cid] else None
            views.append(SourceView(safe_name(frame), cid, images[(frame, cid)], mask))
    cams = [cameras[c] for c in order]
    record: dict[str, Any] = {
        "format": "panoptic",
        "source": str(root.resolve()),
        "to_source": source_transform(np.eye(4), "w2c = world_to_camera; k = K - 0.5 on cx, "
                                      "cy (integer pixel centres)"),
    }
    ups = np.stack([-c.R[1] for c in cams]).mean(axis=0)  # the cameras' mean up (-y)
    up = ups / max(float(np.linalg.norm(ups)), 1e-12)
    return ImportedCapture(cams, [safe_name(f) for f in frames],
                           (float(up[0]), float(up[1]), float(up[2])), views, record, files,
                           points, test_cameras=test or None, masks="subject",
                           poses=PoseSource(files[0], "w2c", "world_to_camera"))


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
