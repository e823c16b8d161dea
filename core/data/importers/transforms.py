"""``transforms.json`` (NeRF synthetic, instant-ngp, nerfstudio): reader and writer.

Conventions of the source: ``transform_matrix`` is camera-to-world with OpenGL camera axes
(x right, y up, looking down -z); the world is z-up. Intrinsics come from ``fl_x/fl_y/cx/cy`` or
from ``camera_angle_x`` (and ``camera_angle_y``), at the top level or per frame (per-frame wins);
``w``/``h`` default to the image's size; ``k1 k2 [k3] p1 p2`` are OpenCV distortion. A folder with
``transforms_{train,val,test}.json`` (NeRF synthetic) is read as one capture, ids prefixed by split.

Multi-frame: entries carrying ``time`` are grouped into frames by distinct time (sorted), and
``camera_id`` (else the file name) says which camera an entry belongs to; a camera must not move
or change intrinsics between frames.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from core.data.capture import (
    Camera,
    Capture,
    CaptureError,
    Problem,
)
from core.data.images import ImageReadError, image_size
from core.data.importers.common import (
    OPENGL_TO_OPENCV,
    ImportedCapture,
    SourceView,
    safe_name,
    source_transform,
)
from core.data.points import PointCloud, read_points_ply
from core.data.schema import extrinsics_problems, intrinsics_problems, read_json

__all__ = ["export_transforms", "find_transforms", "read_transforms"]

_INTRINSIC_KEYS = (
    "fl_x",
    "fl_y",
    "cx",
    "cy",
    "w",
    "h",
    "camera_angle_x",
    "camera_angle_y",
    "k1",
    "k2",
    "k3",
    "k4",
    "p1",
    "p2",
    "camera_model",
)
_ENTRY_KEYS = {"file_path", "transform_matrix", "time", "camera_id", "mask_path", *_INTRINSIC_KEYS}
_SUPPORTED_MODELS = {"OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"}
_IMAGE_GUESS_EXTS = (".png", ".jpg", ".jpeg", ".exr", ".PNG", ".JPG", ".JPEG")


def find_transforms(src: Path) -> list[Path]:
    """The transforms JSON files of a source folder (or the file itself); empty if none."""
    src = Path(src)
    if src.is_file():
        return [src]
    if (src / "transforms.json").is_file():
        return [src / "transforms.json"]
    return [p for s in ("train", "val", "test") if (p := src / f"transforms_{s}.json").is_file()]


def read_transforms(src: str | Path) -> ImportedCapture:
    """Read a transforms.json source; raises :class:`CaptureError` listing every problem."""
    files = find_transforms(Path(src))
    if not files:
        raise CaptureError(
            [Problem(str(src), "no transforms.json (or transforms_{train,val,test}.json) found")]
        )
    problems: list[Problem] = []
    entries: list[dict[str, Any]] = []
    top_extra: dict[str, Any] = {}
    for path in files:
        prefix = path.stem.removeprefix("transforms_") + "_" if len(files) > 1 else ""
        entries += _read_file(path, prefix, problems, top_extra)
    points = _points(files, top_extra, problems)
    if problems:
        raise CaptureError(problems)
    cameras, frames, views, view_extra = _group(entries, problems)
    if problems:
        raise CaptureError(problems)
    record = {
        "format": "transforms",
        "source": str(Path(src).resolve()),
        "files": [p.name for p in files],
        "to_source": source_transform(
            OPENGL_TO_OPENCV,
            "transform_matrix = source_from_world @ inv(world_to_camera)"
            " @ source_camera_from_camera",
        ),
        "frame_times": frames[1],
        "extra": top_extra,
        "views": view_extra,
    }
    record["points"] = 0 if points is None else len(points)
    return ImportedCapture(cameras, frames[0], (0.0, 0.0, 1.0), views, record, list(files),
                           points)


def _points(files: list[Path], top_extra: dict[str, Any],
            problems: list[Problem]) -> PointCloud | None:
    """The point clouds named by ``ply_file_path`` (nerfstudio), merged; None without any."""
    clouds = []
    for path in files:
        rel = top_extra.get(path.name, {}).get("ply_file_path")
        if rel is None:
            continue
        if not isinstance(rel, str) or not rel:
            problems.append(Problem(str(path), f"ply_file_path must be a path, got {rel!r}"))
            continue
        try:
            clouds.append(read_points_ply(path.parent / rel))
        except ValueError as exc:
            problems.append(Problem(str(path), f"ply_file_path: {exc}"))
    if not clouds:
        return None
    colored = all(c.colors is not None for c in clouds)
    return PointCloud(np.concatenate([c.points for c in clouds]),
                      np.concatenate([c.colors for c in clouds]) if colored else None)


def _read_file(
    path: Path, prefix: str, problems: list[Problem], top_extra: dict[str, Any]
) -> list[dict]:
    try:
        data = read_json(path)
    except ValueError as exc:
        problems.append(Problem(str(path), str(exc)))
        return []
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        problems.append(Problem(str(path), "expected an object with a non-empty 'frames' list"))
        return []
    defaults = {k: data[k] for k in _INTRINSIC_KEYS if k in data}
    top_extra[path.name] = {
        k: v for k, v in data.items() if k not in _INTRINSIC_KEYS and k != "frames"
    }
    out = []
    for i, entry in enumerate(data["frames"]):
        where = f"frames[{i}]"
        if (
            not isinstance(entry, dict)
            or "file_path" not in entry
            or "transform_matrix" not in entry
        ):
            problems.append(
                Problem(str(path), f"{where}: needs 'file_path' and 'transform_matrix'")
            )
            continue
        parsed = _parse_entry(path, where, {**defaults, **entry}, prefix, problems)
        if parsed is not None:
            parsed["extra"] = {k: v for k, v in entry.items() if k not in _ENTRY_KEYS}
            out.append(parsed)
    return out


def _resolve_image(base: Path, rel: str) -> Path:
    path = base / rel
    if path.suffix.lower() in _IMAGE_GUESS_EXTS or path.is_file():
        return path
    for ext in _IMAGE_GUESS_EXTS:  # NeRF synthetic leaves the extension out
        if path.with_name(path.name + ext).is_file():
            return path.with_name(path.name + ext)
    return path


def _parse_entry(
    path: Path, where: str, e: dict[str, Any], prefix: str, problems: list[Problem]
) -> dict | None:
    image = _resolve_image(path.parent, str(e["file_path"]))
    n0 = len(problems)
    model = str(e.get("camera_model", "OPENCV")).upper()
    if model not in _SUPPORTED_MODELS:
        problems.append(
            Problem(
                str(path), f"{where}: camera_model {model!r} is not supported (pinhole/OpenCV only)"
            )
        )
    if float(e.get("k4", 0.0) or 0.0) != 0.0:
        problems.append(
            Problem(str(path), f"{where}: k4 is not supported by the OpenCV 5-parameter model")
        )
    try:
        w, h = (int(e["w"]), int(e["h"])) if "w" in e and "h" in e else image_size(image)
        K = _intrinsics(e, w, h)
        c2w = np.array(e["transform_matrix"], dtype=np.float64)
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0, 0, 0, 1]])
        if c2w.shape != (4, 4):
            raise ValueError(f"transform_matrix must be 4x4, got shape {c2w.shape}")
    except ImageReadError as exc:
        problems.append(
            Problem(str(exc.path), f"{exc.message} (needed for the size of {where} in {path.name})")
        )
        return None
    except (KeyError, TypeError, ValueError) as exc:
        problems.append(Problem(str(path), f"{where}: {exc}"))
        return None
    problems.extend(Problem(str(path), f"{where}: {m}") for m in intrinsics_problems(K))
    w2c = np.linalg.inv(c2w @ OPENGL_TO_OPENCV) if np.all(np.isfinite(c2w)) else c2w
    problems.extend(Problem(str(path), f"{where}: {m}") for m in extrinsics_problems(w2c))
    if len(problems) > n0:
        return None
    dist = [float(e.get(k, 0.0) or 0.0) for k in ("k1", "k2", "p1", "p2", "k3")]
    rel = Path(str(e["file_path"])).with_suffix("")
    given = e.get("camera_id")
    mask = e.get("mask_path")
    return {
        # Ids from file names use the bare stem unless stems collide (decided in _group).
        "camera": safe_name(prefix + str(given)) if given else None,
        "stem": safe_name(prefix + rel.name),
        "long": safe_name(prefix + rel.as_posix()),
        "time": e.get("time"),
        "camera_obj": (w, h, K, w2c, tuple(dist) if any(dist) else None),
        "image": image,
        "mask": None if mask is None else path.parent / str(mask),
        "source": str(path),
        "where": where,
        "file_path": e["file_path"],
    }


def _intrinsics(e: dict[str, Any], w: int, h: int) -> np.ndarray:
    if "fl_x" in e:
        fx = float(e["fl_x"])
    elif "camera_angle_x" in e:
        fx = 0.5 * w / math.tan(0.5 * float(e["camera_angle_x"]))
    else:
        raise KeyError("no focal length: give fl_x or camera_angle_x")
    if "fl_y" in e:
        fy = float(e["fl_y"])
    elif "camera_angle_y" in e and "fl_x" not in e:
        fy = 0.5 * h / math.tan(0.5 * float(e["camera_angle_y"]))
    else:
        fy = fx
    cx = float(e.get("cx", w / 2.0))
    cy = float(e.get("cy", h / 2.0))
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _group(entries: list[dict], problems: list[Problem]):
    """Entries to (cameras, (frame names, times), views, per-view extras)."""
    bad = [e for e in entries if not isinstance(e["time"], (int, float, type(None)))]
    for e in bad:
        problems.append(
            Problem(e["source"], f"{e['where']}: 'time' must be a number, got {e['time']!r}")
        )
    if bad:
        return [], ([], []), [], {}
    times = sorted({e["time"] for e in entries if e["time"] is not None})
    if times and any(e["time"] is None for e in entries):
        problems.append(Problem(entries[0]["source"], "some frames have 'time' and some do not"))
        return [], ([], []), [], {}
    names = [f"{i:06d}" for i in range(max(1, len(times)))]
    frame_of = {t: names[i] for i, t in enumerate(times)}
    by_frame: dict[str, list[str]] = {}
    for e in entries:
        by_frame.setdefault(frame_of.get(e["time"], names[0]), []).append(e["stem"])
    stems_unique = all(len(set(s)) == len(s) for s in by_frame.values())
    for e in entries:
        if e["camera"] is None:
            e["camera"] = e["stem"] if stems_unique else e["long"]
    cameras: dict[str, Camera] = {}
    views: list[SourceView] = []
    extra: dict[str, Any] = {}
    seen: set[tuple[str, str]] = set()
    for e in entries:
        frame = frame_of.get(e["time"], names[0])
        cid = e["camera"]
        if (frame, cid) in seen:
            problems.append(
                Problem(e["source"], f"{e['where']}: duplicate camera id {cid!r} in frame {frame}")
            )
            continue
        seen.add((frame, cid))
        w, h, K, w2c, dist = e["camera_obj"]
        cam = Camera(cid, w, h, K, w2c, dist)
        if cid in cameras and not _same_camera(cameras[cid], cam):
            problems.append(
                Problem(e["source"], f"{e['where']}: camera {cid!r} changes pose or intrinsics")
            )
        cameras.setdefault(cid, cam)
        views.append(SourceView(frame, cid, e["image"], e["mask"]))
        extra[f"{frame}/{cid}"] = {"file_path": e["file_path"], **e["extra"]}
    return list(cameras.values()), (names, times), views, extra


def _same_camera(a: Camera, b: Camera, tol: float = 1e-9) -> bool:
    return (
        (a.width, a.height) == (b.width, b.height)
        and np.allclose(a.K, b.K, atol=tol)
        and np.allclose(a.world_to_camera, b.world_to_camera, atol=tol)
        and (a.distortion or (0,) * 5) == (b.distortion or (0,) * 5)
    )


def export_transforms(capture: Capture, dst: str | Path) -> Path:
    """Write ``capture`` as an instant-ngp/nerfstudio-style transforms.json with images under dst.

    Intrinsics are written per entry (cameras may differ); multi-frame captures carry ``time``
    (the frame index) and ``camera_id``.
    """
    dst = Path(dst)
    entries = []
    for i, frame in enumerate(capture.frames):
        for cam in capture.cameras:
            src = capture.image_path(frame, cam.id)
            if src is None:
                raise FileNotFoundError(f"{capture.root}/images/{frame}/{cam.id}.*: missing image")
            rel = f"images/{frame}/{cam.id}{src.suffix}"
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst / rel)
            c2w = np.linalg.inv(cam.world_to_camera) @ OPENGL_TO_OPENCV
            entry: dict[str, Any] = {
                "file_path": rel,
                "transform_matrix": c2w.tolist(),
                "camera_id": cam.id,
                "fl_x": cam.K[0, 0],
                "fl_y": cam.K[1, 1],
                "cx": cam.K[0, 2],
                "cy": cam.K[1, 2],
                "w": cam.width,
                "h": cam.height,
            }
            if len(capture.frames) > 1:
                entry["time"] = i
            if cam.distortion is not None:
                entry.update(dict(zip(("k1", "k2", "p1", "p2", "k3"), cam.distortion)))
            mask = capture.mask_path(frame, cam.id)
            if mask is not None:
                entry["mask_path"] = f"masks/{frame}/{cam.id}.png"
                (dst / entry["mask_path"]).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(mask, dst / entry["mask_path"])
            entries.append(entry)
    path = dst / "transforms.json"
    path.write_text(json.dumps({"frames": entries}, indent=1))
    return path
