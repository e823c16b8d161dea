"""What every importer produces, and the one writer of the canonical layout they all share.

A reader turns its source into an :class:`ImportedCapture` without writing anything; problems with
the source are collected and raised together as :class:`CaptureError`. :func:`write_canonical`
then copies the files (never symlinks, never touching the source), writes capture.json with the
import record, keeps the source's metadata files verbatim under ``source/``, validates the result
in a scratch folder and only then moves it into place.
"""

from __future__ import annotations

import os
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from core.data.capture import (
    Camera,
    Capture,
    CaptureError,
    Problem,
    save_capture,
)
from core.data.headers import HeaderError, ImageHeader, check_pixels, read_other_header
from core.data.points import POINTS_PLY, PointCloud, write_points_ply
from core.data.rules import safe_name  # the one rule for ids; the importers take it from here
from core.data.validate import validate_capture

__all__ = [
    "OPENGL_TO_OPENCV",
    "ImportedCapture",
    "PoseSource",
    "SourceView",
    "safe_name",
    "source_transform",
    "write_canonical",
]

# Flips y and z: OpenGL camera axes (x right, y up, looking down -z) to OpenCV (y down, z forward).
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])

_COPY_EXTS = {".png": ".png", ".jpg": ".jpg", ".jpeg": ".jpg", ".exr": ".exr"}
_CONVERT_EXTS = {".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm"}


@dataclass(frozen=True)
class SourceView:
    """Where one view's files are in the source."""

    frame: str
    camera: str
    image: Path
    mask: Path | None = None
    normal: Path | None = None


@dataclass(frozen=True)
class PoseSource:
    """Where a reader's poses are written in its source, for the rig checks' messages
    (`core.data.importers.rig`)."""

    file: Path
    """The metadata file that holds them."""
    field: str
    """The field, as the source names it (``w2c``, ``frames[*].transform_matrix``)."""
    holds: Literal["world_to_camera", "camera_to_world", "projection"]
    """What the format says the field holds (a projection cannot be the wrong way round)."""
    up: tuple[float, float, float] | None = None
    """The world's up where the format fixes it (transforms.json: +z), else None."""
    solved: bool = False
    """The poses were written by the program that solved them (COLMAP's model), in its one
    convention: never checked for the wrong direction, since no hand conversion stands between
    the solver and the file, and a room scanned from its middle (cameras looking outward, which
    the direction rule may take for an inverted rig) is an ordinary COLMAP capture."""


@dataclass
class ImportedCapture:
    """A source read into canonical terms, ready to be written."""

    cameras: list[Camera]
    frames: list[str]
    up: tuple[float, float, float]
    views: list[SourceView]
    record: dict[str, Any]
    """The import record kept in capture.json: format, source, transform back, unused keys."""
    metadata_files: list[Path] = field(default_factory=list)
    """Source files copied verbatim into ``source/`` so nothing is lost."""
    points: PointCloud | None = None
    """The source's point cloud (COLMAP points3D, a nerfstudio PLY), written as points.ply."""
    test_cameras: list[str] | None = None
    """The cameras the source's dataset holds out for evaluation (its published split), kept
    as capture.json `test_cameras`; None when it has none."""
    masks: str = "matte"
    """What its masks are (`core.data.Capture.masks`)."""
    poses: PoseSource | None = None
    """Where the poses come from, for the rig checks (`core.data.importers.rig`)."""


def source_transform(camera_axes: np.ndarray, pose: str) -> dict[str, Any]:
    """The import record's way back to the source's coordinates.

    ``source_from_world`` maps capture world points to source world points (importers keep the
    source world, so it is the identity); ``source_camera_from_camera`` maps OpenCV camera axes to
    the source's camera axes; ``pose`` says how the source's pose is recovered from both.
    """
    return {
        "source_from_world": np.eye(4).tolist(),
        "source_camera_from_camera": np.asarray(camera_axes, dtype=np.float64).tolist(),
        "pose": pose,
    }


def _target_ext(path: Path) -> str | None:
    ext = path.suffix.lower()
    if ext in _COPY_EXTS:
        return _COPY_EXTS[ext]
    if ext in _CONVERT_EXTS:
        return ".png"
    return None


def _check_sources(imported: ImportedCapture) -> list[Problem]:
    problems: list[Problem] = []
    for v in imported.views:
        for kind, path in (("image", v.image), ("mask", v.mask), ("normal", v.normal)):
            if path is None:
                continue
            if not path.is_file():
                problems.append(
                    Problem(str(path), f"{kind} of camera {v.camera!r} frame {v.frame!r} not found")
                )
            elif _target_ext(path) is None:
                problems.append(Problem(str(path), f"unsupported {kind} file type {path.suffix!r}"))
            elif kind == "mask" and _target_ext(path) == ".exr":
                problems.append(
                    Problem(str(path), "masks must be PNG (or a lossless type we convert)")
                )
    for meta in imported.metadata_files:
        if not meta.is_file():
            problems.append(Problem(str(meta), "source metadata file not found"))
    return problems


def _place(src: Path, dst_stem: Path, link: bool, max_pixels: int | None) -> Path:
    """Copy (or hard-link) one file into the capture; converts exotic types losslessly to PNG
    (after their header says they are within ``max_pixels``)."""
    ext = _target_ext(src)
    dst = dst_stem.with_suffix(ext)
    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.suffix.lower() in _CONVERT_EXTS:
        try:
            width, height = read_other_header(src)
            check_pixels(ImageHeader(width, height, "png"), max_pixels)
        except HeaderError as exc:
            raise CaptureError([Problem(str(src), str(exc))]) from None
        arr = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
        if arr is None or not cv2.imwrite(str(dst), arr):
            raise CaptureError([Problem(str(src), "cannot decode image to convert it to PNG")])
        return dst
    if link:
        try:
            os.link(src, dst)
            return dst
        except OSError:
            pass  # other filesystem or not permitted: fall back to a copy
    shutil.copyfile(src, dst)
    return dst


def write_canonical(
    imported: ImportedCapture,
    out: str | os.PathLike[str],
    *,
    link: bool = False,
    max_pixels: int | None = None,
) -> Capture:
    """Write ``imported`` to ``out`` in the canonical layout and return the loaded capture.

    ``out`` must not exist (or be an empty folder). Raises :class:`CaptureError` naming source files
    when anything is wrong; on failure nothing is left at ``out``.
    """
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise CaptureError(
            [Problem(str(out), "output exists and is not an empty folder; choose a new --out")]
        )
    problems = _check_sources(imported)
    if problems:
        raise CaptureError(problems)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.partial-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        placed = _write_files(imported, tmp, link, max_pixels)
        capture = Capture(
            tmp,
            tuple(imported.cameras),
            tuple(imported.frames),
            imported.up,
            import_record=imported.record,
            test_cameras=None if imported.test_cameras is None else tuple(imported.test_cameras),
            masks=imported.masks,  # type: ignore[arg-type]
        )
        save_capture(capture)
        problems = validate_capture(tmp, max_pixels=max_pixels)
        if problems:
            # Point at the source file the user has to fix, not at our scratch copy
            # (validation names files relative to the capture).
            raise CaptureError(
                [Problem(placed.get(p.path, str(out / p.path)), p.message) for p in problems]
            )
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    capture.root = out
    return capture


def _write_files(
    imported: ImportedCapture, root: Path, link: bool, max_pixels: int | None
) -> dict[str, str]:
    """Place every view's files; returns {written path relative to ``root``: source path} for
    error messages."""
    placed: dict[str, str] = {}
    for v in imported.views:
        for sub, src in (("images", v.image), ("masks", v.mask), ("normals", v.normal)):
            if src is not None:
                dst = _place(src, root / sub / v.frame / v.camera, link, max_pixels)
                placed[dst.relative_to(root).as_posix()] = str(src)
    if imported.points is not None and len(imported.points):
        write_points_ply(root / POINTS_PLY, imported.points)
    seen: set[str] = set()
    for meta in imported.metadata_files:
        name = meta.name if meta.name not in seen else f"{len(seen)}_{meta.name}"
        seen.add(name)
        dst = root / "source" / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(meta, dst)
    return placed
