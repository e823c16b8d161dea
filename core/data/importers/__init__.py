"""Importers from other capture formats into the canonical layout (one module per format)."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from core.data.capture import Capture, CaptureError, Problem
from core.data.importers.actorshq import find_calibration, read_actorshq
from core.data.importers.colmap import find_model, read_colmap
from core.data.importers.common import ImportedCapture, SourceView, write_canonical
from core.data.importers.idr import find_cameras_npz, read_idr
from core.data.importers.panoptic import find_meta, read_panoptic
from core.data.importers.rig import settle_rig
from core.data.importers.transforms import find_transforms, read_transforms

__all__ = [
    "FORMATS",
    "IMPORTERS",
    "Importer",
    "ImportedCapture",
    "SourceView",
    "detect_format",
    "import_capture",
    "read_source",
    "write_canonical",
]


@dataclass(frozen=True)
class Importer:
    """One source format: how to recognise it and how to read it."""

    finds: Callable[[Path], bool]
    """True when a source folder (or file) has this format's files."""
    read: Callable[[Path], ImportedCapture]
    """The reader (raises CaptureError listing every problem)."""
    summary: str
    """What it reads, in a few words (the CLI's help, the API's schema)."""


# The one list of capture formats: the CLI, the API's schema (and so openapi.yaml) and the web
# page (GET /v1/info) read it.
IMPORTERS: dict[str, Importer] = {
    "transforms": Importer(lambda src: bool(find_transforms(src)), read_transforms,
                           "transforms.json (NeRF synthetic, instant-ngp, nerfstudio)"),
    "colmap": Importer(lambda src: src.is_dir() and find_model(src) is not None, read_colmap,
                       "a COLMAP sparse model (text or binary)"),
    "actorshq": Importer(lambda src: find_calibration(src) is not None, read_actorshq,
                         "ActorsHQ calibration.csv + rgbs/ + masks/"),
    "idr": Importer(lambda src: find_cameras_npz(src) is not None, read_idr,
                    "IDR / NeuS cameras.npz + image/ + mask/"),
    "panoptic": Importer(lambda src: find_meta(src) is not None, read_panoptic,
                         "CMU Panoptic as Dynamic 3D Gaussians prepares it: train_meta.json, "
                         "test_meta.json, ims/, seg/"),
}
FORMATS: tuple[str, ...] = tuple(IMPORTERS)


def detect_format(src: str | os.PathLike[str]) -> str:
    """Guess the source format from the files present; raises CaptureError when unclear."""
    src = Path(src)
    if not src.exists():
        raise CaptureError([Problem(str(src), "source not found")])
    found = [name for name, importer in IMPORTERS.items() if importer.finds(src)]
    if len(found) != 1:
        what = "no known format" if not found else f"several formats ({', '.join(found)})"
        raise CaptureError([Problem(str(src), f"{what}: pass --format " + "|".join(FORMATS))])
    return found[0]


def read_source(src: str | os.PathLike[str], fmt: str = "auto") -> ImportedCapture:
    """Read a source of format ``fmt`` (or detected) without writing anything. Every reader's
    cameras pass the rig checks here (`core.data.importers.rig.settle_rig`: a mirrored world
    mirrored back, mixed handedness and inverted poses refused)."""
    if fmt == "auto":
        fmt = detect_format(src)
    if fmt not in IMPORTERS:
        raise ValueError(f"fmt: expected auto or one of {FORMATS}, got {fmt!r}")
    return settle_rig(IMPORTERS[fmt].read(Path(src)))


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
