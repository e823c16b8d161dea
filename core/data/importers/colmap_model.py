"""COLMAP sparse model files (``cameras`` and ``images``, ``.txt`` or ``.bin``) read into typed
records: each file's size is bounded before it is read (cameras as metadata; images, which
hold every image's 2D points, streamed a line or a record at a time), record counts are bounded
before a record is read, tokens are ASCII numbers, and every problem names the file and the
line or record (``images.txt: line 7: camera_id: ...``)."""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, BinaryIO

from pydantic import Field

from core.data.capture import CaptureError, Problem
from core.data.importers.records import (
    MAX_CAMERAS,
    MAX_VIEWS,
    FieldError,
    Number,
    Record,
    Side,
    SourcePath,
    checked,
    listof,
)
from core.data.rules import MAX_METADATA_BYTES

__all__ = ["MAX_MODEL_BYTES", "MODELS", "MODEL_IDS", "ColmapCamera", "ColmapImage",
           "read_model"]

# model id: (name, number of params)
MODELS: dict[int, tuple[str, int]] = {
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
MODEL_IDS = {name: mid for mid, (name, _) in MODELS.items()}
MAX_MODEL_BYTES = 4 << 30
"""Largest images or points3D file read (streamed, a line or a record at a time: they hold
every image's 2D points, gigabytes in large models); cameras files are metadata
(core.data.rules.MAX_METADATA_BYTES)."""


class ColmapCamera(Record):
    """A line of cameras.txt or a record of cameras.bin."""

    id: Annotated[int, Field(ge=-(2**31), lt=2**31)]
    model: str
    width: Side
    height: Side
    params: listof(Number, 12)  # type: ignore[valid-type]


class ColmapImage(Record):
    """The first line of an image in images.txt, or a record of images.bin."""

    id: Annotated[int, Field(ge=-(2**31), lt=2**31)]
    qvec: listof(Number, 4, 4)  # type: ignore[valid-type]
    tvec: listof(Number, 3, 3)  # type: ignore[valid-type]
    camera_id: Annotated[int, Field(ge=-(2**31), lt=2**31)]
    name: SourcePath


_INT = re.compile(r"[+-]?[0-9]{1,18}", re.ASCII)
_FLOAT = re.compile(r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]{1,4})?", re.ASCII)


def _token(text: str, field: str, pattern: re.Pattern) -> int | float:
    if not pattern.fullmatch(text):
        what = "an integer" if pattern is _INT else "a number"
        raise FieldError(field, f"{text[:40]!r} is not {what}")
    return int(text) if pattern is _INT else float(text)


def _lines(path: Path, limit: int) -> Iterator[tuple[int, str]]:
    """(line number, line) of a text model file, comments and blank lines left out; the
    file's size is bounded before it is read, and it is read a line at a time."""
    size = path.stat().st_size
    if size > limit:
        raise ValueError(f"is {size} bytes; this COLMAP file may have {limit}")
    with open(path, encoding="utf-8") as fh:
        for n, line in enumerate(fh, 1):
            if not line.startswith("#"):
                yield n, line


def _camera_txt(n: int, line: str, path: Path, problems: list[Problem]) -> ColmapCamera | None:
    f = line.split()
    try:
        if len(f) < 4:
            raise FieldError("line", "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        values = {"id": _token(f[0], "id", _INT), "model": f[1],
                  "width": _token(f[2], "width", _INT), "height": _token(f[3], "height", _INT),
                  "params": [_token(x, f"params[{i}]", _FLOAT) for i, x in enumerate(f[4:])]}
    except FieldError as exc:
        problems.append(Problem(str(path), f"line {n}: {exc}"))
        return None
    return checked(ColmapCamera, values, path, f"line {n}", problems)


def _image_txt(n: int, line: str, path: Path, problems: list[Problem]) -> ColmapImage | None:
    f = line.split(maxsplit=9)
    try:
        if len(f) < 10:
            raise FieldError("line", "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        nums = [_token(x, k, _FLOAT) for x, k in zip(f[1:8], ("qw", "qx", "qy", "qz", "tx",
                                                                "ty", "tz"))]
        values = {"id": _token(f[0], "id", _INT), "qvec": nums[:4], "tvec": nums[4:],
                  "camera_id": _token(f[8], "camera_id", _INT), "name": f[9].rstrip()}
    except FieldError as exc:
        problems.append(Problem(str(path), f"line {n}: {exc}"))
        return None
    return checked(ColmapImage, values, path, f"line {n}", problems)


def _read_cameras_txt(path: Path, problems: list[Problem]) -> list[ColmapCamera]:
    out = []
    for n, line in _lines(path, MAX_METADATA_BYTES):
        if line.strip():
            if len(out) == MAX_CAMERAS:
                raise ValueError(f"lists more than {MAX_CAMERAS} cameras")
            cam = _camera_txt(n, line, path, problems)
            out += [cam] if cam is not None else []
    return out


def _read_images_txt(path: Path, problems: list[Problem]) -> list[ColmapImage]:
    out, count = [], 0
    # Each image is two lines; the second (2D points) may be empty, so pair by position.
    for i, (n, line) in enumerate(_lines(path, MAX_MODEL_BYTES)):
        if i % 2 or not line.strip():
            continue
        count += 1
        if count > MAX_VIEWS:
            raise ValueError(f"lists more than {MAX_VIEWS} images")
        image = _image_txt(n, line, path, problems)
        out += [image] if image is not None else []
    return out


def _unpack(fh: BinaryIO, fmt: str) -> tuple:
    size = struct.calcsize(fmt)
    data = fh.read(size)
    if len(data) != size:
        raise ValueError("file ends early (truncated?)")
    return struct.unpack(fmt, data)


def _count(fh: BinaryIO, most: int, what: str, size: int, least_bytes: int) -> int:
    """The record count a binary model file opens with, bounded by `most` and by what its size
    can hold (`least_bytes` a record) before a record is read."""
    (n,) = _unpack(fh, "<Q")
    if n > most or n * least_bytes > size:
        raise ValueError(f"declares {n} {what}; it can hold at most "
                         f"{min(most, size // least_bytes)}")
    return n


def _read_cameras_bin(path: Path, problems: list[Problem]) -> list[ColmapCamera]:
    out = []
    size = path.stat().st_size
    if size > MAX_METADATA_BYTES:
        raise ValueError(f"is {size} bytes; this COLMAP file may have {MAX_METADATA_BYTES}")
    with open(path, "rb") as fh:
        for i in range(_count(fh, MAX_CAMERAS, "cameras", size, 24 + 8 * 3)):
            cid, mid, w, h = _unpack(fh, "<iiQQ")
            if mid not in MODELS:
                raise ValueError(f"camera {i}: unknown camera model id {mid}")
            name, nparams = MODELS[mid]
            cam = checked(ColmapCamera, {"id": cid, "model": name, "width": w, "height": h,
                                         "params": list(_unpack(fh, f"<{nparams}d"))},
                          path, f"camera {i}", problems)
            out += [cam] if cam is not None else []
    return out


def _read_name(fh: BinaryIO, i: int) -> str:
    name = bytearray()
    while (ch := fh.read(1)) not in (b"\x00", b""):
        name += ch
        if len(name) > 1024:
            raise ValueError(f"image {i}: name longer than 1024 bytes (or not NUL-ended)")
    try:
        return name.decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"image {i}: name is not UTF-8") from None


def _read_images_bin(path: Path, problems: list[Problem]) -> list[ColmapImage]:
    out = []
    size = path.stat().st_size
    if size > MAX_MODEL_BYTES:
        raise ValueError(f"is {size} bytes; this COLMAP file may have {MAX_MODEL_BYTES}")
    with open(path, "rb") as fh:
        for i in range(_count(fh, MAX_VIEWS, "images", size, 64 + 1 + 8)):
            vals = _unpack(fh, "<i7di")
            name = _read_name(fh, i)
            (npts,) = _unpack(fh, "<Q")
            if npts * 24 > size - fh.tell():
                raise ValueError(f"image {i}: declares {npts} points, past the end (truncated?)")
            fh.seek(24 * npts, 1)
            image = checked(ColmapImage, {"id": vals[0], "qvec": list(vals[1:5]),
                                          "tvec": list(vals[5:8]), "camera_id": vals[8],
                                          "name": name}, path, f"image {i}", problems)
            out += [image] if image is not None else []
    return out


def read_model(model: Path) -> tuple[dict[int, ColmapCamera], list[ColmapImage], str]:
    """Cameras by id, images and the extension (.txt or .bin) of the model in `model`;
    CaptureError naming the file and each problem."""
    ext = ".txt" if (model / "cameras.txt").is_file() else ".bin"
    problems: list[Problem] = []
    cams: list[ColmapCamera] = []
    images: list[ColmapImage] = []
    for name in ("cameras", "images"):
        path = model / f"{name}{ext}"
        readers = {"cameras": (_read_cameras_txt, _read_cameras_bin),
                   "images": (_read_images_txt, _read_images_bin)}[name]
        try:
            got = readers[ext == ".bin"](path, problems)
        except (OSError, ValueError, UnicodeDecodeError, struct.error) as exc:
            text = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
            raise CaptureError([Problem(str(path), f"cannot parse COLMAP {name}: {text}")]) \
                from None
        if name == "cameras":
            cams = got
        else:
            images = got
    by_id: dict[int, ColmapCamera] = {}
    for cam in cams:
        if cam.id in by_id:
            problems.append(Problem(str(model / f"cameras{ext}"), f"camera id {cam.id} is "
                                    "listed twice"))
        by_id[cam.id] = cam
    if problems:
        raise CaptureError(problems)
    return by_id, images, ext
