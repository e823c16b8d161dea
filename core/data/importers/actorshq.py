"""ActorsHQ-style captures (``calibration.csv`` + ``rgbs/`` + ``masks/``): reader and writer.

``calibration.csv`` has one row per camera: ``name,w,h,rx,ry,rz,tx,ty,tz,fx,fy,px,py`` where
(rx, ry, rz) is the axis-angle rotation and (tx, ty, tz) the position of the camera in the world
(camera-to-world, OpenCV camera axes) and fx, fy, px, py are normalized by the image width and
height. Images are ``rgbs/<cam>/<cam>_rgb<frame>.(jpg|png)``, masks
``masks/<cam>/<cam>_mask<frame>.png``; the frame number becomes the frame name.
"""

from __future__ import annotations

import csv
import io
import itertools
import re
import shutil
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
from pydantic import AfterValidator, ConfigDict
from pydantic_core import PydanticCustomError

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
from core.data.importers.records import (
    MAX_CAMERAS,
    Number,
    Record,
    Side,
    SourceName,
    checked,
    read_text,
)
from core.data.rules import path_problem
from core.data.schema import extrinsics_problems, intrinsics_problems

__all__ = ["export_actorshq", "find_calibration", "read_actorshq"]

_COLUMNS = ("name", "w", "h", "rx", "ry", "rz", "tx", "ty", "tz", "fx", "fy", "px", "py")


def find_calibration(src: Path) -> Path | None:
    src = Path(src)
    if src.is_file() and src.name.endswith(".csv"):
        return src
    path = src / "calibration.csv"
    return path if path.is_file() else None


def _rodrigues(rvec: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(rvec))
    if theta < 1e-15:
        return np.eye(3)
    k = rvec / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx


def _axis_angle(R: np.ndarray) -> np.ndarray:
    # cv2.Rodrigues handles the theta ~ pi case that the trace formula gets wrong.
    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].ravel()


def _component(value: str) -> str:
    problem = path_problem(value)
    if problem is not None or "/" in value:
        raise PydanticCustomError("source_path", "{name} names a folder under rgbs/ and masks/: "
                                  "one file name, {problem}", {"name": repr(value)[:60],
                                                              "problem": problem or "no '/'"})
    return value


class ActorsHQRow(Record):
    """A row of calibration.csv. CSV cells are text, so numbers are parsed from it (and must
    be finite numbers: "nan" or "1e999" are refused)."""

    model_config = ConfigDict(strict=False, frozen=True, extra="forbid")
    name: Annotated[SourceName, AfterValidator(_component)]
    w: Side
    h: Side
    rx: Number
    ry: Number
    rz: Number
    tx: Number
    ty: Number
    tz: Number
    fx: Number
    fy: Number
    px: Number
    py: Number


def _parse_row(row: ActorsHQRow, where: str, problems: list[Problem]) -> Camera | None:
    w, h = row.w, row.h
    K = np.array([[row.fx * w, 0, row.px * w], [0, row.fy * h, row.py * h], [0, 0, 1.0]])
    c2w = np.eye(4)
    with np.errstate(all="ignore"):  # a huge rotation vector overflows: refused below
        c2w[:3, :3] = _rodrigues(np.array([row.rx, row.ry, row.rz]))
    c2w[:3, 3] = [row.tx, row.ty, row.tz]
    bad = intrinsics_problems(K) + extrinsics_problems(c2w, "the camera's pose")
    problems.extend(Problem(where, m) for m in bad)
    return None if bad else Camera(safe_name(row.name), w, h, K, np.linalg.inv(c2w), None)


def _read_csv(path: Path, problems: list[Problem]) -> tuple[list[Camera], dict[str, str]]:
    try:
        text = read_text(path)
        rows = list(itertools.islice(csv.DictReader(io.StringIO(text, newline="")),
                                     MAX_CAMERAS + 1))
    except csv.Error as exc:
        problems.append(Problem(str(path), f"cannot read CSV: {exc}"))
        return [], {}
    except CaptureError as exc:
        problems.extend(exc.problems)
        return [], {}
    header = set(rows[0]) if rows else set()
    missing = [c for c in _COLUMNS if c not in header]
    if not rows or missing:
        problems.append(
            Problem(str(path), f"expected columns {','.join(_COLUMNS)}; missing {missing}")
        )
        return [], {}
    if len(rows) > MAX_CAMERAS:
        problems.append(Problem(str(path), f"lists more than {MAX_CAMERAS} cameras"))
        return [], {}
    cameras, names = [], {}
    for i, raw in enumerate(rows):
        row = checked(ActorsHQRow, {k: raw.get(k) for k in _COLUMNS}, path, f"row {i + 2}",
                      problems)
        cam = None if row is None else _parse_row(row, f"{path} row {i + 2} ({row.name})",
                                                  problems)
        if cam is None:
            continue
        if cam.id in names:
            problems.append(Problem(str(path), f"row {i + 2}: duplicate camera id {cam.id!r}"))
            continue
        names[cam.id] = row.name
        cameras.append(cam)
    return cameras, names


def _find_frames(
    src: Path, names: dict[str, str], problems: list[Problem]
) -> dict[str, dict[str, Path]]:
    """{frame: {camera id: image path}} from rgbs/<cam>/<cam>_rgb<frame>.<ext>."""
    found: dict[str, dict[str, Path]] = {}
    for cid, name in names.items():
        folder = src / "rgbs" / name
        if not folder.is_dir():
            problems.append(Problem(str(folder), f"image folder of camera {name!r} not found"))
            continue
        pattern = re.compile(rf"^{re.escape(name)}_rgb([0-9]{{1,9}})\.(jpg|jpeg|png)$",
                             re.IGNORECASE | re.ASCII)
        for path in sorted(folder.iterdir()):
            m = pattern.match(path.name)
            if m:
                found.setdefault(m.group(1), {})[cid] = path
    for frame, per_cam in found.items():
        for cid, name in names.items():
            if cid not in per_cam and (src / "rgbs" / name).is_dir():
                problems.append(
                    Problem(
                        str(src / "rgbs" / name / f"{name}_rgb{frame}.jpg"),
                        f"missing image of camera {name!r} for frame {frame}",
                    )
                )
    if not found and not problems:
        problems.append(
            Problem(str(src / "rgbs"), "no images named <cam>/<cam>_rgb<frame>.jpg found")
        )
    return found


def read_actorshq(src: str | Path) -> ImportedCapture:
    """Read an ActorsHQ-style source; raises :class:`CaptureError` listing every problem."""
    calib = find_calibration(Path(src))
    if calib is None:
        raise CaptureError([Problem(str(src), "calibration.csv not found")])
    root = calib.parent
    problems: list[Problem] = []
    cameras, names = _read_csv(calib, problems)
    frames = _find_frames(root, names, problems) if names else {}
    if problems:
        raise CaptureError(problems)
    views = []
    for frame in sorted(frames):
        for cid, name in names.items():
            mask = root / "masks" / name / f"{name}_mask{frame}.png"
            views.append(
                SourceView(
                    safe_name(frame), cid, frames[frame][cid], mask if mask.is_file() else None
                )
            )
    record: dict[str, Any] = {
        "format": "actorshq",
        "source": str(root.resolve()),
        "to_source": source_transform(
            np.eye(4), "[Rodrigues(rx,ry,rz) | tx,ty,tz] = source_from_world @ inv(world_to_camera)"
        ),
        "camera_names": names,
    }
    ups = np.stack([-c.R[1] for c in cameras]).mean(axis=0)
    up = ups / max(np.linalg.norm(ups), 1e-12)
    return ImportedCapture(
        cameras,
        [safe_name(f) for f in sorted(frames)],
        (float(up[0]), float(up[1]), float(up[2])),
        views,
        record,
        [calib],
        poses=PoseSource(calib, "rx, ry, rz, tx, ty, tz", "camera_to_world"),
    )


def export_actorshq(capture: Capture, dst: str | Path) -> Path:
    """Write ``capture`` as ``dst/calibration.csv`` + ``rgbs/`` (+ ``masks/``); returns the CSV.

    Frames are numbered by their index (6 digits); distortion cannot be expressed and is refused.
    """
    dst = Path(dst)
    dst.mkdir(parents=True, exist_ok=True)
    rows = []
    for cam in capture.cameras:
        if cam.distortion is not None:
            raise ValueError(
                f"capture: camera {cam.id!r} has distortion, which calibration.csv cannot hold"
            )
        c2w = cam.camera_to_world
        r = _axis_angle(c2w[:3, :3])
        w, h = cam.width, cam.height
        vals = [
            w,
            h,
            *r,
            *c2w[:3, 3],
            cam.K[0, 0] / w,
            cam.K[1, 1] / h,
            cam.K[0, 2] / w,
            cam.K[1, 2] / h,
        ]
        rows.append([cam.id] + [repr(float(x)) if not isinstance(x, int) else str(x) for x in vals])
    path = dst / "calibration.csv"
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(_COLUMNS)
        writer.writerows(rows)
    for i, frame in enumerate(capture.frames):
        for cam in capture.cameras:
            src = capture.image_path(frame, cam.id)
            if src is None:
                raise FileNotFoundError(f"{capture.root}/images/{frame}/{cam.id}.*: missing image")
            out = dst / "rgbs" / cam.id / f"{cam.id}_rgb{i:06d}{src.suffix}"
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, out)
            mask = capture.mask_path(frame, cam.id)
            if mask is not None:
                out = dst / "masks" / cam.id / f"{cam.id}_mask{i:06d}.png"
                out.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(mask, out)
    return path
