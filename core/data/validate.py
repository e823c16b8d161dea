"""Validation of a capture in the canonical layout: every problem in one pass, nothing written.

Checks capture.json (schema, intrinsics, rotations, duplicate ids) and then every file under
``images/``, ``masks/`` and ``normals/``: presence, decodability, size against the camera, file
type, and that nothing is a symlink or resolves outside the capture folder. ``gt/`` and
``source/`` (ground truth and verbatim import sources) are not capture content and are skipped.

Problems name files relative to the capture folder (``images/000000/cam03.png``), the way the
capture's author knows them, never by where it happens to be on this machine. An optional
``points.ply`` must be a readable point cloud with finite coordinates.
"""

from __future__ import annotations

import os
from pathlib import Path

from core.data.capture import (
    CAPTURE_JSON,
    IMAGE_EXTS,
    MASK_EXTS,
    NORMAL_EXTS,
    Capture,
    CaptureError,
    Problem,
    valid_name,
)
from core.data.images import ImageReadError, verify_image
from core.data.points import POINTS_PLY, read_points_ply
from core.data.schema import parse_capture_json, read_json

__all__ = ["check_capture", "validate_capture"]

_CONTENT_DIRS: dict[str, tuple[str, ...]] = {
    "images": IMAGE_EXTS,
    "masks": MASK_EXTS,
    "normals": NORMAL_EXTS,
}
_MASK_MODES = {"1", "L", "LA", "I;16", "I", "RGB", "RGBA", "P"}


def check_capture(root: str | os.PathLike[str], *, max_pixels: int | None = None) -> Capture:
    """Validate and load; raises :class:`CaptureError` listing every problem found. Images of
    more than ``max_pixels`` pixels (default: core.data.headers' process default) are refused
    from their header, before they are decoded."""
    capture, problems = _validate(Path(root), max_pixels)
    if problems or capture is None:
        raise CaptureError(problems)
    return capture


def validate_capture(
    root: str | os.PathLike[str], *, max_pixels: int | None = None
) -> list[Problem]:
    """Every problem with the capture at ``root`` (empty when it is valid). Reads only."""
    return _validate(Path(root), max_pixels)[1]


def _validate(root: Path, max_pixels: int | None) -> tuple[Capture | None, list[Problem]]:
    if not root.is_dir():
        return None, [Problem(str(root), "capture folder not found or not a folder")]
    capture, problems = _collect(root, max_pixels)
    prefix = str(root) + os.sep
    return capture, [
        Problem(p.path[len(prefix):].replace(os.sep, "/"), p.message)
        if p.path.startswith(prefix) else p
        for p in problems
    ]


def _collect(root: Path, max_pixels: int | None) -> tuple[Capture | None, list[Problem]]:
    capture, problems, data = _check_json(root)
    # Cameras whose entry is broken still own their files: check those too (without a size).
    sizes: dict[str, tuple[int, int] | None] = {}
    for entry in data.get("cameras", []) if isinstance(data.get("cameras"), list) else []:
        if isinstance(entry, dict) and valid_name(entry.get("id")):
            sizes.setdefault(entry["id"], None)
    if capture is not None:
        sizes.update({c.id: (c.width, c.height) for c in capture.cameras})
    names = (set(capture.frames), set(sizes)) if capture is not None else None
    for sub, exts in _CONTENT_DIRS.items():
        problems += _scan_tree(root, sub, exts, names)
    problems += _check_points(root)
    if capture is None:
        return None, problems
    if not (root / "images").is_dir() or (root / "images").is_symlink():
        problems.append(Problem(str(root / "images"), "images/ folder missing"))
        return capture, problems
    for frame in dict.fromkeys(capture.frames):
        for cam_id, size in sizes.items():
            problems += _check_view(root, frame, cam_id, size, max_pixels)
    return capture, problems


def _check_points(root: Path) -> list[Problem]:
    path = root / POINTS_PLY
    if path.is_symlink():
        return [Problem(str(path), "is a symlink; captures must contain real files")]
    if not path.exists():
        return []
    if not path.is_file():
        return [Problem(str(path), "must be a PLY file, not a folder")]
    try:
        cloud = read_points_ply(path)
    except ValueError as exc:
        return [Problem(str(path), str(exc).removeprefix(f"{path}: "))]
    if not len(cloud):
        return [Problem(str(path), "has no points; leave it out to triangulate instead")]
    return []


def _check_json(root: Path) -> tuple[Capture | None, list[Problem], dict]:
    path = root / CAPTURE_JSON
    if path.is_symlink():
        return None, [Problem(str(path), "is a symlink; captures must contain real files")], {}
    if not path.is_file():
        return None, [Problem(str(path), "capture.json not found (is this a capture folder?)")], {}
    try:
        data = read_json(path)
    except ValueError as exc:
        return None, [Problem(str(path), f"capture.json: {exc}")], {}
    capture, problems = parse_capture_json(data, root)
    # parse_capture_json names the file relatively; make it point at this capture.
    problems = [Problem(str(path), p.message) for p in problems]
    return capture, problems, data if isinstance(data, dict) else {}


def _scan_tree(
    root: Path, sub: str, exts: tuple[str, ...], names: tuple[set[str], set[str]] | None
) -> list[Problem]:
    """Symlinks, escapes, stray folders and unsupported file types under ``root/sub``."""
    top = root / sub
    if top.is_symlink():
        return [Problem(str(top), "is a symlink; captures must contain real folders")]
    if not top.is_dir():
        return []
    problems: list[Problem] = []
    real_root = root.resolve()
    for dirpath, dirnames, filenames in os.walk(top, followlinks=False):
        here = Path(dirpath)
        depth = len(here.relative_to(top).parts)
        for name in sorted(dirnames + filenames):
            path = here / name
            if path.is_symlink():
                target = os.readlink(path)
                leaves = not path.resolve().is_relative_to(real_root)
                what = "points outside the capture folder" if leaves else "is a symlink"
                problems.append(
                    Problem(str(path), f"{what} (-> {target}); captures must contain real files")
                )
                continue
            if not path.resolve().is_relative_to(real_root):
                problems.append(Problem(str(path), "resolves outside the capture folder"))
                continue
            problems += _check_entry(path, depth, name in dirnames, exts, names)
        dirnames[:] = [d for d in dirnames if depth == 0 and not (here / d).is_symlink()]
    return problems


def _check_entry(
    path: Path,
    depth: int,
    is_dir: bool,
    exts: tuple[str, ...],
    names: tuple[set[str], set[str]] | None,
) -> list[Problem]:
    frames, cameras = names if names is not None else (None, None)
    if depth == 0:
        if not is_dir:
            return [Problem(str(path), "unexpected file; expected one folder per frame")]
        if frames is not None and path.name not in frames:
            return [
                Problem(
                    str(path), f"folder for frame {path.name!r}, which capture.json does not list"
                )
            ]
        return []
    if is_dir:
        return [Problem(str(path), "unexpected folder; expected <camera>.<ext> files")]
    ext = path.suffix
    if ext not in exts:
        allowed = ", ".join(exts)
        return [
            Problem(
                str(path), f"unsupported file type {ext or '(none)'!r} here (expected {allowed})"
            )
        ]
    if cameras is not None and path.stem not in cameras:
        return [
            Problem(str(path), f"file for camera {path.stem!r}, which capture.json does not list")
        ]
    return []


def _check_view(
    root: Path, frame: str, cam: str, size: tuple[int, int] | None, max_pixels: int | None
) -> list[Problem]:
    problems: list[Problem] = []
    for sub, exts in _CONTENT_DIRS.items():
        found = [root / sub / frame / f"{cam}{e}" for e in exts]
        found = [p for p in found if p.exists() or p.is_symlink()]
        if not found:
            if sub == "images":
                expected = "|".join(e.lstrip(".") for e in exts)
                problems.append(
                    Problem(
                        str(root / sub / frame / f"{cam}.{expected}"),
                        f"missing image of camera {cam!r} in frame {frame!r}",
                    )
                )
            continue
        if len(found) > 1:
            problems.append(
                Problem(
                    str(found[0]), f"several {sub} files for one view: {[p.name for p in found]}"
                )
            )
        path = found[0]
        if path.is_symlink() or not path.resolve().is_relative_to(root.resolve()):
            continue  # already reported by the tree scan; never read through a link
        problems += _check_file(path, sub, cam, size, max_pixels)
    return problems


def _check_file(
    path: Path, sub: str, cam: str, size: tuple[int, int] | None, max_pixels: int | None
) -> list[Problem]:
    try:
        w, h, mode = verify_image(path, max_pixels)
    except ImageReadError as exc:
        return [Problem(str(path), exc.message)]
    problems: list[Problem] = []
    if size is not None and (w, h) != size:
        problems.append(
            Problem(str(path), f"size {w}x{h} disagrees with camera {cam!r} ({size[0]}x{size[1]})")
        )
    if sub == "masks" and mode not in _MASK_MODES:
        problems.append(Problem(str(path), f"mask has unsupported pixel mode {mode!r}"))
    if sub == "normals" and mode in ("1", "L", "LA", "I;16", "I", "P", "F1"):
        problems.append(Problem(str(path), f"normal map needs 3 channels, got mode {mode!r}"))
    if sub == "images" and mode in ("1", "P", "I", "CMYK"):
        problems.append(
            Problem(str(path), f"image has unsupported pixel mode {mode!r} (use RGB, RGBA or L)")
        )
    return problems
