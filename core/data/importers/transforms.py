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
from pathlib import Path, PurePosixPath
from typing import Annotated, Any

import numpy as np
from pydantic import Field

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
    PoseSource,
    SourceView,
    safe_name,
    source_transform,
)
from core.data.importers.records import (
    MAX_VIEWS,
    FieldError,
    IdOrNumber,
    Number,
    Record,
    Side,
    SourcePath,
    checked,
    listof,
    load_json,
    matrix,
)
from core.data.points import PointCloud, read_points_ply
from core.data.rules import name_problem
from core.data.schema import extrinsics_problems, intrinsics_problems

__all__ = ["export_transforms", "find_transforms", "read_transforms"]

_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
                   "k1", "k2", "k3", "k4", "p1", "p2", "camera_model")
_SUPPORTED_MODELS = {"OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"}
_IMAGE_GUESS_EXTS = (".png", ".jpg", ".jpeg", ".exr", ".PNG", ".JPG", ".JPEG")


class _Intrinsics(Record):
    """Intrinsics, at the top level (defaults) or per entry (they win)."""

    fl_x: Number | None = None
    fl_y: Number | None = None
    cx: Number | None = None
    cy: Number | None = None
    w: Side | None = None
    h: Side | None = None
    camera_angle_x: Number | None = None
    camera_angle_y: Number | None = None
    k1: Number | None = None
    k2: Number | None = None
    k3: Number | None = None
    k4: Number | None = None
    p1: Number | None = None
    p2: Number | None = None
    camera_model: Annotated[str, Field(max_length=64)] | None = None


class TransformsEntry(_Intrinsics):
    """One entry of ``frames``: an image and its camera-to-world (OpenGL axes)."""

    file_path: SourcePath
    transform_matrix: matrix(4, 4, least_rows=3)  # type: ignore[valid-type]
    time: Number | None = None
    camera_id: IdOrNumber | None = None
    mask_path: SourcePath | None = None


class TransformsFile(_Intrinsics):
    """A transforms JSON file; each entry of ``frames`` is parsed on its own (a
    `TransformsEntry`), so one bad entry does not hide the problems of the others."""

    frames: listof(dict[str, Any], MAX_VIEWS)  # type: ignore[valid-type]
    ply_file_path: SourcePath | None = None


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
    docs: dict[Path, TransformsFile] = {}
    for path in files:
        try:
            docs[path] = load_json(path, TransformsFile)
        except CaptureError as exc:
            problems.extend(exc.problems)
    for path, doc in docs.items():
        prefix = path.stem.removeprefix("transforms_") + "_" if len(files) > 1 else ""
        entries += _read_file(path, doc, prefix, problems, top_extra)
    points = _points(docs, problems)
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
                           points, poses=PoseSource(files[0], "frames[*].transform_matrix",
                                                    "camera_to_world", up=(0.0, 0.0, 1.0)))


def _points(docs: dict[Path, TransformsFile], problems: list[Problem]) -> PointCloud | None:
    """The point clouds named by ``ply_file_path`` (nerfstudio), merged; None without any."""
    clouds = []
    for path, doc in docs.items():
        if doc.ply_file_path is None:
            continue
        try:
            clouds.append(read_points_ply(path.parent / doc.ply_file_path))
        except ValueError as exc:
            problems.append(Problem(str(path), f"ply_file_path: {exc}"))
    if not clouds:
        return None
    colored = all(c.colors is not None for c in clouds)
    return PointCloud(np.concatenate([c.points for c in clouds]),
                      np.concatenate([c.colors for c in clouds]) if colored else None)


def _set(record: _Intrinsics) -> dict[str, Any]:
    return {k: getattr(record, k) for k in _INTRINSIC_KEYS if getattr(record, k) is not None}


def _read_file(path: Path, doc: TransformsFile, prefix: str, problems: list[Problem],
               top_extra: dict[str, Any]) -> list[dict]:
    defaults = _set(doc)
    top_extra[path.name] = {**(doc.model_extra or {}), **(
        {"ply_file_path": doc.ply_file_path} if doc.ply_file_path is not None else {})}
    out = []
    for i, raw in enumerate(doc.frames):
        entry = checked(TransformsEntry, raw, path, f"frames[{i}]", problems)
        if entry is None:
            continue
        parsed = _parse_entry(path, f"frames[{i}]", entry, {**defaults, **_set(entry)}, prefix,
                              problems)
        if parsed is not None:
            parsed["extra"] = dict(entry.model_extra or {})
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


def _ids(entry: TransformsEntry, prefix: str) -> tuple[str | None, str, str]:
    """(camera id given, id from the file's stem, id from its whole path); FieldError naming
    the field whose name cannot become an id."""
    rel = PurePosixPath(entry.file_path)
    rel = rel.with_name(rel.stem) if rel.stem else rel
    for field, name in (("file_path", rel.as_posix()), ("camera_id", entry.camera_id)):
        problem = None if name is None else name_problem(prefix + str(name))
        if problem is not None:
            raise FieldError(field, f"{prefix + str(name)!r} {problem}")
    given = None if entry.camera_id is None else safe_name(prefix + str(entry.camera_id))
    return given, safe_name(prefix + rel.name), safe_name(prefix + rel.as_posix())


def _parse_entry(path: Path, where: str, entry: TransformsEntry, e: dict[str, Any],
                 prefix: str, problems: list[Problem]) -> dict | None:
    image = _resolve_image(path.parent, entry.file_path)
    n0 = len(problems)
    model = str(e.get("camera_model", "OPENCV")).upper()
    if model not in _SUPPORTED_MODELS:
        problems.append(Problem(str(path), f"{where}: camera_model {model!r} is not supported "
                                           "(pinhole/OpenCV only)"))
    if e.get("k4", 0.0) != 0.0:
        problems.append(Problem(str(path), f"{where}: k4 is not supported by the OpenCV "
                                           "5-parameter model"))
    try:
        w, h = (e["w"], e["h"]) if "w" in e and "h" in e else image_size(image)
        K = _intrinsics(e, w, h)
        camera, stem_id, long_id = _ids(entry, prefix)
    except ImageReadError as exc:
        problems.append(
            Problem(str(exc.path), f"{exc.message} (needed for the size of {where} in {path.name})")
        )
        return None
    except FieldError as exc:
        problems.append(Problem(str(path), f"{where}.{exc.field}: {exc.message}"))
        return None
    c2w = np.array(entry.transform_matrix, dtype=np.float64)
    if c2w.shape == (3, 4):
        c2w = np.vstack([c2w, [0, 0, 0, 1]])
    problems.extend(Problem(str(path), f"{where}: {m}") for m in intrinsics_problems(K))
    c2w_cv = c2w @ OPENGL_TO_OPENCV
    bad = extrinsics_problems(c2w_cv, "transform_matrix", proper=False)  # rig checks: det -1
    problems.extend(Problem(str(path), f"{where}: {m}") for m in bad)
    if len(problems) > n0:
        return None
    w2c = np.linalg.inv(c2w_cv)  # rigid, so invertible: the checks above made sure
    dist = [float(e.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")]
    return {
        # Ids from file names use the bare stem unless stems collide (decided in _group).
        "camera": camera,
        "stem": stem_id,
        "long": long_id,
        "time": entry.time,
        "camera_obj": (w, h, K, w2c, tuple(dist) if any(dist) else None),
        "image": image,
        "mask": None if entry.mask_path is None else path.parent / entry.mask_path,
        "source": str(path),
        "where": where,
        "file_path": entry.file_path,
    }


def _focal(e: dict[str, Any], key: str, size: int) -> float:
    """The focal length from a field of view `e[key]`, which must be in (0, pi)."""
    angle = e[key]
    if not 0.0 < angle < math.pi:
        raise FieldError(key, f"must be a field of view in (0, pi) radians, got {angle}")
    return 0.5 * size / math.tan(0.5 * angle)


def _intrinsics(e: dict[str, Any], w: int, h: int) -> np.ndarray:
    if "fl_x" in e:
        fx = float(e["fl_x"])
    elif "camera_angle_x" in e:
        fx = _focal(e, "camera_angle_x", w)
    else:
        raise FieldError("fl_x", "no focal length: give fl_x or camera_angle_x")
    if "fl_y" in e:
        fy = float(e["fl_y"])
    elif "camera_angle_y" in e and "fl_x" not in e:
        fy = _focal(e, "camera_angle_y", h)
    else:
        fy = fx
    cx = float(e.get("cx", w / 2.0))
    cy = float(e.get("cy", h / 2.0))
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _group(entries: list[dict], problems: list[Problem]):
    """Entries to (cameras, (frame names, times), views, per-view extras)."""
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
