"""Importers from other capture formats into the canonical layout (one module per format)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from core.data.capture import Capture, CaptureError, Problem
from core.data.importers.actorshq import find_calibration, read_actorshq
from core.data.importers.colmap import find_model, read_colmap
from core.data.importers.common import ImportedCapture, SourceView, write_canonical
from core.data.importers.idr import find_cameras_npz, read_idr
from core.data.importers.transforms import find_transforms, read_transforms

__all__ = [
    "FORMATS",
    "ImportedCapture",
    "SourceView",
    "detect_format",
    "import_capture",
    "read_source",
    "write_canonical",
]

Format = Literal["transforms", "colmap", "actorshq", "idr"]
FORMATS: tuple[str, ...] = ("transforms", "colmap", "actorshq", "idr")


def detect_format(src: str | os.PathLike[str]) -> Format:
    """Guess the source format from the files present; raises CaptureError when unclear."""
    src = Path(src)
    if not src.exists():
        raise CaptureError([Problem(str(src), "source not found")])
    found: list[Format] = []
    if find_transforms(src):
        found.append("transforms")
    if src.is_dir() and find_model(src) is not None:
        found.append("colmap")
    if find_calibration(src) is not None:
        found.append("actorshq")
    if find_cameras_npz(src) is not None:
        found.append("idr")
    if len(found) != 1:
        what = "no known format" if not found else f"several formats ({', '.join(found)})"
        raise CaptureError([Problem(str(src), f"{what}: pass --format " + "|".join(FORMATS))])
    return found[0]


def read_source(src: str | os.PathLike[str], fmt: str = "auto") -> ImportedCapture:
    """Read a source of format ``fmt`` (or detected) without writing anything."""
    if fmt == "auto":
        fmt = detect_format(src)
    if fmt == "transforms":
        return read_transforms(Path(src))
    if fmt == "colmap":
        return read_colmap(Path(src))
    if fmt == "actorshq":
        return read_actorshq(Path(src))
    if fmt == "idr":
        return read_idr(Path(src))
    raise ValueError(f"fmt: expected auto or one of {FORMATS}, got {fmt!r}")


def import_capture(
    src: str | os.PathLike[str],
    out: str | os.PathLike[str],
    fmt: str = "auto",
    *,
    link: bool = False,
    max_pixels: int | None = None,
) -> Capture:
    """Import ``src`` into a new canonical capture at ``out`` and return it (validated; images
    of more than ``max_pixels`` pixels are refused, see :func:`core.data.check_capture`)."""
    return write_canonical(read_source(src, fmt), out, link=link, max_pixels=max_pixels)
