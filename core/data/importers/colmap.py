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
from typing import Any, BinaryIO

import numpy as np

from core.data.capture import (
    Camera,
    Capture,
    CaptureError,
    Problem,
)
from core.data.importers.common import ImportedCapture, SourceView, safe_name, source_transform
from core.data.points import PointCloud, read_colmap_points, read_points_ply, write_colmap_points
from core.data.schema import extrinsics_problems, intrinsics_problems
from core.rotations import quat_to_rotmat, rotmat_to_quat

__all__ = ["export_colmap", "find_model", "read_colmap"]

# model id: (name, number of params)
_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
}
_MODEL_IDS = {name: mid for mid, (name, _) in _MODELS.items()}


def find_model(src: Path) -> Path | None:
    """The folder holding cameras/images model files, searched where COLMAP usually puts it."""
    for cand in (src / "sparse" / "0", src / "sparse", src / "colmap" / "sparse" / "0", src):
        for ext in (".txt", ".bin"):
            if (cand / f"cameras{ext}").is_file() and (cand / f"images{ext}").is_file():
                return cand
    return None


def _intrinsics(model: str, p: list[float]) -> tuple[np.ndarray, tuple | None]:
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


def _read_cameras_txt(path: Path) -> dict[int, tuple[str, int, int, list[float]]]:
    out = {}
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            f = line.split()
            out[int(f[0])] = (f[1], int(f[2]), int(f[3]), [float(x) for x in f[4:]])
    return out


def _read_images_txt(path: Path) -> list[tuple[int, np.ndarray, np.ndarray, int, str]]:
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    out = []
    # Each image is two lines; the second (2D points) may be empty, so pair by position.
    for header in lines[0::2]:
        if not header.strip():
            continue
        f = header.split(maxsplit=9)
        out.append((int(f[0]), np.array(f[1:5], float), np.array(f[5:8], float), int(f[8]), f[9]))
    return out


def _unpack(fh: BinaryIO, fmt: str) -> tuple:
    size = struct.calcsize(fmt)
    data = fh.read(size)
    if len(data) != size:
        raise ValueError("file ends early (truncated?)")
    return struct.unpack(fmt, data)


def _read_cameras_bin(path: Path) -> dict[int, tuple[str, int, int, list[float]]]:
    out = {}
    with open(path, "rb") as fh:
        (n,) = _unpack(fh, "<Q")
        for _ in range(n):
            cid, mid, w, h = _unpack(fh, "<iiQQ")
            if mid not in _MODELS:
                raise ValueError(f"unknown camera model id {mid}")
            name, nparams = _MODELS[mid]
            out[cid] = (name, w, h, list(_unpack(fh, f"<{nparams}d")))
    return out


def _read_images_bin(path: Path) -> list[tuple[int, np.ndarray, np.ndarray, int, str]]:
    out = []
    with open(path, "rb") as fh:
        (n,) = _unpack(fh, "<Q")
        for _ in range(n):
            vals = _unpack(fh, "<i7di")
            name = b""
            while (ch := fh.read(1)) not in (b"\x00", b""):
                name += ch
            (npts,) = _unpack(fh, "<Q")
            fh.seek(24 * npts, 1)
            out.append((vals[0], np.array(vals[1:5]), np.array(vals[5:8]), vals[8], name.decode()))
    return out


def _read_model(model: Path) -> tuple[dict, list, str]:
    ext = ".txt" if (model / "cameras.txt").is_file() else ".bin"
    for name in ("cameras", "images"):
        path = model / f"{name}{ext}"
        try:
            if name == "cameras":
                cams = _read_cameras_txt(path) if ext == ".txt" else _read_cameras_bin(path)
            else:
                images = _read_images_txt(path) if ext == ".txt" else _read_images_bin(path)
        except (OSError, ValueError, IndexError, UnicodeDecodeError, struct.error) as exc:
            raise CaptureError([Problem(str(path), f"cannot parse COLMAP {name}: {exc}")]) from None
    return cams, images, ext


def read_colmap(src: str | Path) -> ImportedCapture:
    """Read a COLMAP source folder; raises :class:`CaptureError` listing every problem."""
    src = Path(src)
    model = find_model(src)
    if model is None:
        raise CaptureError(
            [Problem(str(src), "no COLMAP model (cameras/images .txt or .bin) found")]
        )
    cams, images, ext = _read_model(model)
    problems: list[Problem] = []
    posed = _pose_images(model, ext, cams, images, problems)
    if not posed and not problems:
        problems.append(Problem(str(model / f"images{ext}"), "lists no images"))
    if problems:
        raise CaptureError(problems)
    grouping = _group_frames(posed)
    if grouping is None:
        grouping = {name: ("000000", name.rsplit(".", 1)[0]) for name, *_ in posed}
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
    try:
        points = read_colmap_points(model)
    except ValueError as exc:
        raise CaptureError([Problem(str(model), f"cannot parse COLMAP points3D: {exc}")]) from None
    record["points"] = 0 if points is None else len(points)
    frames = sorted({v.frame for v in views})
    cam_list = list(cameras.values())
    return ImportedCapture(cam_list, frames, _estimate_up(cam_list), views, record, meta, points)


def _pose_images(model: Path, ext: str, cams: dict, images: list, problems: list[Problem]) -> list:
    """(name, image id, COLMAP camera id, Camera) per image; bad entries become problems."""
    where = str(model / f"images{ext}")
    out = []
    for image_id, q, t, cam_id, name in images:
        label = f"image {image_id} ({name})"
        if cam_id not in cams:
            problems.append(Problem(where, f"{label}: camera id {cam_id} not in cameras{ext}"))
            continue
        model_name, w, h, params = cams[cam_id]
        try:
            K, dist = _intrinsics(model_name, params)
        except (ValueError, IndexError) as exc:
            problems.append(Problem(str(model / f"cameras{ext}"), f"camera {cam_id}: {exc}"))
            continue
        w2c = np.eye(4)
        w2c[:3, :3] = quat_to_rotmat(q) if np.linalg.norm(q) > 0 else np.zeros((3, 3))
        w2c[:3, 3] = t
        bad = intrinsics_problems(K) + extrinsics_problems(w2c)
        problems.extend(Problem(where, f"{label}: {m}") for m in bad)
        out.append((name, image_id, cam_id, Camera("x", int(w), int(h), K, w2c, dist)))
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
            fh.write(struct.pack("<iiQQ", cid, _MODEL_IDS[name], w, h))
            fh.write(struct.pack(f"<{len(params)}d", *params))
    with open(model / "images.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(images)))
        for iid, q, t, cid, name in images:
            fh.write(struct.pack("<i7di", iid, *q, *t, cid))
            fh.write(name.encode() + b"\x00")
            fh.write(struct.pack("<Q", 0))
