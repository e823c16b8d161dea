"""COLMAP sparse models (``cameras``/``images`` as ``.txt`` or ``.bin``): reader and writer.

COLMAP already uses OpenCV camera axes, world-to-camera poses (quaternion w,x,y,z + t) and pixel
centres at +0.5, so poses and intrinsics carry over unchanged. Every image becomes a camera.
Multi-frame: when every image name is ``<frame>/<camera>.<ext>``, every frame has the same
cameras and each camera keeps its pose, names group into frames; otherwise (a rig stored as
``<camera>/<shot>.jpg``, say) all images form one frame, ids from the full name.
``points3D`` (text or binary) becomes the capture's ``points.ply`` (the seed of training); it and
the other model files also stay verbatim in ``source/``.
"""

from __future__ import annotations

import shutil
import struct
from pathlib import Path
from typing import Any

import numpy as np

from core.data.capture import (
    Camera,
    Capture,
    CaptureError,
    Problem,
)
from core.data.importers.common import (
    ImportedCapture,
    PoseSource,
    SourceView,
    safe_name,
    source_transform,
)
from core.data.importers.colmap_model import (
    MAX_MODEL_BYTES,
    MODEL_IDS,
    MODELS,
    ColmapCamera,
    ColmapImage,
    read_model,
)
from core.data.points import PointCloud, read_colmap_points, read_points_ply, write_colmap_points
from core.data.rules import name_problem
from core.data.schema import extrinsics_problems, intrinsics_problems
from core.rotations import quat_to_rotmat, rotmat_to_quat

__all__ = ["export_colmap", "find_model", "read_colmap"]

def find_model(src: Path) -> Path | None:
    """The folder holding cameras/images model files, searched where COLMAP usually puts it."""
    for cand in (src / "sparse" / "0", src / "sparse", src / "colmap" / "sparse" / "0", src):
        for ext in (".txt", ".bin"):
            if (cand / f"cameras{ext}").is_file() and (cand / f"images{ext}").is_file():
                return cand
    return None


def _intrinsics(model: str, p: list[float]) -> tuple[np.ndarray, tuple | None]:
    if model not in MODEL_IDS:
        raise ValueError(f"camera model {model[:40]!r} is not one of COLMAP's")
    if len(p) != MODELS[MODEL_IDS[model]][1]:
        raise ValueError(f"{model} takes {MODELS[MODEL_IDS[model]][1]} parameters, got {len(p)}")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        k = p[3:] + [0.0, 0.0]
        dist = [k[0], k[1], 0.0, 0.0, 0.0] if model != "SIMPLE_PINHOLE" else [0.0] * 5
    elif model in ("PINHOLE", "OPENCV", "FULL_OPENCV"):
        fx, fy, cx, cy = p[:4]
        rest = p[4:] + [0.0] * 5
        if model == "FULL_OPENCV" and any(rest[5:8]):
            raise ValueError(
                "FULL_OPENCV with k4..k6 != 0 is not supported (OpenCV 5-parameter model only)"
            )
        dist = rest[:5]
    else:
        raise ValueError(f"camera model {model} is not supported (pinhole/OpenCV models only)")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return K, (tuple(float(d) for d in dist) if any(dist) else None)


def read_colmap(src: str | Path) -> ImportedCapture:
    """Read a COLMAP source folder; raises :class:`CaptureError` listing every problem."""
    src = Path(src)
    model = find_model(src)
    if model is None:
        raise CaptureError(
            [Problem(str(src), "no COLMAP model (cameras/images .txt or .bin) found")]
        )
    cams, images, ext = read_model(model)
    problems: list[Problem] = []
    posed = _pose_images(model, ext, cams, images, problems)
    if not posed and not problems:
        problems.append(Problem(str(model / f"images{ext}"), "lists no images"))
    if problems:
        raise CaptureError(problems)
    grouping = _group_frames(posed)
    if grouping is None:
        grouping = {name: ("000000", name.rsplit(".", 1)[0]) for name, *_ in posed}
    problems += _name_problems(grouping, str(model / f"images{ext}"))
    if problems:
        raise CaptureError(problems)
    image_root = src / "images" if (src / "images").is_dir() else src
    cameras: dict[str, Camera] = {}
    views: list[SourceView] = []
    record_views: dict[str, Any] = {}
    seen: set[tuple[str, str]] = set()
    for name, image_id, cam_id, cam in posed:
        frame, cid = (safe_name(x) for x in grouping[name])
        if (frame, cid) in seen:  # the same name twice, or names equal once made safe
            problems.append(
                Problem(str(model / f"images{ext}"), f"{name}: duplicate camera id {cid!r}")
            )
            continue
        seen.add((frame, cid))
        cameras.setdefault(
            cid, Camera(cid, cam.width, cam.height, cam.K, cam.world_to_camera, cam.distortion)
        )
        views.append(SourceView(frame, cid, image_root / name))
        record_views[f"{frame}/{cid}"] = {"name": name, "image_id": image_id, "camera_id": cam_id}
    if problems:
        raise CaptureError(problems)
    meta = [p for p in sorted(model.iterdir()) if p.is_file() and p.suffix in (".txt", ".bin")]
    record = {
        "format": "colmap",
        "source": str(src.resolve()),
        "model": str(model.relative_to(src)) if model != src else ".",
        "frames_from": "<frame>/<camera> image names"
        if len({v.frame for v in views}) > 1
        else "single frame",
        "to_source": source_transform(
            np.eye(4), "[R | t] of qvec, tvec = world_to_camera @ inv(source_from_world)"
        ),
        "views": record_views,
    }
    points = _points(model)
    record["points"] = 0 if points is None else len(points)
    frames = sorted({v.frame for v in views})
    cam_list = list(cameras.values())
    poses = PoseSource(model / f"images{ext}", "qvec, tvec", "world_to_camera",
                       solved=True)
    return ImportedCapture(cam_list, frames, _estimate_up(cam_list), views, record, meta, points,
                           poses=poses)


def _points(model: Path) -> PointCloud | None:
    """points3D (text or binary), bounded by its size before it is read."""
    try:
        for path in (model / "points3D.txt", model / "points3D.bin"):
            if path.is_file() and path.stat().st_size > MAX_MODEL_BYTES:
                raise ValueError(f"{path.name} is {path.stat().st_size} bytes; this COLMAP "
                                 f"file may have {MAX_MODEL_BYTES}")
        return read_colmap_points(model)
    except ValueError as exc:
        raise CaptureError([Problem(str(model), f"cannot parse COLMAP points3D: {exc}")]) from None


def _pose_images(model: Path, ext: str, cams: dict[int, ColmapCamera],
                 images: list[ColmapImage], problems: list[Problem]) -> list:
    """(name, image id, COLMAP camera id, Camera) per image; bad entries become problems."""
    where = str(model / f"images{ext}")
    out = []
    for image in images:
        label = f"image {image.id} ({image.name})"
        cam = cams.get(image.camera_id)
        if cam is None:
            problems.append(Problem(where, f"{label}: camera id {image.camera_id} not in "
                                           f"cameras{ext}"))
            continue
        try:
            K, dist = _intrinsics(cam.model, list(cam.params))
        except ValueError as exc:
            problems.append(Problem(str(model / f"cameras{ext}"), f"camera {cam.id}: {exc}"))
            continue
        q = np.asarray(image.qvec, np.float64)
        with np.errstate(all="ignore"):  # a huge quaternion overflows: refused below
            norm = float(np.linalg.norm(q))
        if not (np.isfinite(norm) and norm > 1e-12):
            problems.append(Problem(where, f"{label}: qvec must be a non-zero quaternion of "
                                           f"finite size, got {list(image.qvec)}"))
            continue
        w2c = np.eye(4)
        w2c[:3, :3] = quat_to_rotmat(q / norm)
        w2c[:3, 3] = image.tvec
        bad = intrinsics_problems(K) + extrinsics_problems(w2c)
        problems.extend(Problem(where, f"{label}: {m}") for m in bad)
        out.append((image.name, image.id, cam.id,
                    Camera("x", cam.width, cam.height, K, w2c, dist)))
    return out


def _name_problems(grouping: dict[str, tuple[str, str]], where: str) -> list[Problem]:
    """The image names whose frame or camera part cannot become an id."""
    out = []
    for name, parts in grouping.items():
        for what, part in zip(("frame", "camera"), parts):
            problem = name_problem(part)
            if problem is not None:
                out.append(Problem(where, f"{name!r}: {what} {part!r} {problem}"))
    return out


def _group_frames(posed: list) -> dict[str, tuple[str, str]] | None:
    """{name: (frame, camera)} when names read as ``<frame>/<camera>.<ext>`` consistently: every
    frame has the same cameras and each camera keeps its pose. None otherwise (one frame then)."""
    parts = {name: Path(name).parts for name, *_ in posed}
    if len(posed) < 2 or any(len(p) != 2 for p in parts.values()):
        return None
    grouping = {name: (p[0], Path(p[1]).stem) for name, p in parts.items()}
    if len(set(grouping.values())) != len(grouping):
        return None
    frames: dict[str, set[str]] = {}
    first: dict[str, Camera] = {}
    for name, _, _, cam in posed:
        frame, cid = grouping[name]
        frames.setdefault(frame, set()).add(cid)
        ref = first.setdefault(cid, cam)
        same = (ref.width, ref.height, ref.distortion) == (cam.width, cam.height, cam.distortion)
        if not (
            same
            and np.allclose(ref.world_to_camera, cam.world_to_camera, atol=1e-9)
            and np.allclose(ref.K, cam.K, atol=1e-9)
        ):
            return None
    sets = list(frames.values())
    if len(sets) < 2 or any(s != sets[0] for s in sets):
        return None
    return grouping


def _estimate_up(cameras: list[Camera]) -> tuple[float, float, float]:
    # COLMAP worlds have no fixed up; cameras are usually held upright, so their mean -y axis is it.
    ups = np.stack([-c.R[1] for c in cameras])
    up = ups.mean(axis=0)
    up = up / max(np.linalg.norm(up), 1e-12)
    return (float(up[0]), float(up[1]), float(up[2]))


def _model_of(cam: Camera) -> tuple[str, list[float]]:
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    if cam.distortion is None:
        return "PINHOLE", [fx, fy, cx, cy]
    if cam.distortion[4] == 0:
        return "OPENCV", [fx, fy, cx, cy, *cam.distortion[:4]]
    return "FULL_OPENCV", [fx, fy, cx, cy, *cam.distortion, 0.0, 0.0, 0.0]


def export_colmap(capture: Capture, dst: str | Path, *, binary: bool = False,
                  points: PointCloud | None = None) -> Path:
    """Write ``capture`` as ``dst/sparse/0`` (text or binary) + ``dst/images``; returns sparse/0.
    ``points3D`` holds `points` (default: the capture's points.ply; empty without one)."""
    dst = Path(dst)
    model = dst / "sparse" / "0"
    model.mkdir(parents=True, exist_ok=True)
    multi = len(capture.frames) > 1
    images = []
    for frame in capture.frames:
        for ci, cam in enumerate(capture.cameras):
            src = capture.image_path(frame, cam.id)
            if src is None:
                raise FileNotFoundError(f"{capture.root}/images/{frame}/{cam.id}.*: missing image")
            name = f"{frame}/{cam.id}{src.suffix}" if multi else f"{cam.id}{src.suffix}"
            (dst / "images" / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst / "images" / name)
            images.append((len(images) + 1, rotmat_to_quat(cam.R), cam.t, ci + 1, name))
    cams = {i + 1: (*_model_of(c), c.width, c.height) for i, c in enumerate(capture.cameras)}
    (_write_bin if binary else _write_txt)(model, cams, images)
    if points is None and capture.points_path() is not None:
        points = read_points_ply(capture.points_path())
    write_colmap_points(model, points, binary=binary)
    return model


def _write_txt(model: Path, cams: dict, images: list) -> None:
    lines = [
        f"{cid} {name} {w} {h} " + " ".join(repr(float(p)) for p in params)
        for cid, (name, params, w, h) in cams.items()
    ]
    (model / "cameras.txt").write_text("# Camera list\n" + "\n".join(lines) + "\n")
    out = ["# Image list"]
    for iid, q, t, cid, name in images:
        out.append(f"{iid} " + " ".join(repr(float(x)) for x in (*q, *t)) + f" {cid} {name}")
        out.append("")
    (model / "images.txt").write_text("\n".join(out) + "\n")


def _write_bin(model: Path, cams: dict, images: list) -> None:
    with open(model / "cameras.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(cams)))
        for cid, (name, params, w, h) in cams.items():
            fh.write(struct.pack("<iiQQ", cid, MODEL_IDS[name], w, h))
            fh.write(struct.pack(f"<{len(params)}d", *params))
    with open(model / "images.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(images)))
        for iid, q, t, cid, name in images:
            fh.write(struct.pack("<i7di", iid, *q, *t, cid))
            fh.write(name.encode() + b"\x00")
            fh.write(struct.pack("<Q", 0))
