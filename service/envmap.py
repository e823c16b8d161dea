"""Environment maps clients upload for relighting: a readable OpenEXR or Radiance HDR image,
equirectangular (width = 2 x height), RGB radiance that is finite, not negative and not all
zero: what a render job would refuse later (core.relight.envmap) is refused here, before it is
stored. The header is read first (core.data.headers), so an empty, truncated, wrong-format or
too large file is refused before any decoding."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.data.images import ImageReadError
from core.relight.envmap import check_radiance, project_sh9, read_envmap

__all__ = ["CONTENT_TYPES", "EnvmapError", "EnvmapInfo", "inspect_envmap"]

CONTENT_TYPES = {".exr": "image/x-exr", ".hdr": "image/vnd.radiance"}


class EnvmapError(ValueError):
    """The file `name` is not a usable environment map; `problem` says why (no server path)."""

    def __init__(self, name: str, problem: str):
        super().__init__(f"{name}: {problem}")
        self.name, self.problem = name, problem


@dataclass(frozen=True)
class EnvmapInfo:
    width: int
    height: int
    channels: int
    sh9: list[list[float]]
    """(9, 3) radiance SH in the map's own frame (poles on +z, unrotated): what the page's
    player relights with, turned into the capture's up frame and rotated there."""


def inspect_envmap(path: Path, name: str, max_pixels: int) -> EnvmapInfo:
    """Decode the whole image at `path`, known to the client as `name`, and check it
    (EnvmapError naming `name` otherwise)."""
    suffix = Path(name).suffix.lower()
    if suffix not in CONTENT_TYPES:
        raise EnvmapError(name, f"unsupported file type {suffix!r}; send .exr or .hdr")
    try:
        image = read_envmap(path, max_pixels)
    except ImageReadError as exc:
        raise EnvmapError(name, exc.message) from None
    try:
        check_radiance(image, name)
    except ValueError as exc:  # "envmap: <name>: <problem>"
        raise EnvmapError(name, str(exc).split(f"{name}: ", 1)[-1]) from None
    height, width, channels = image.shape
    sh9 = project_sh9(np.clip(image[..., :3].astype(np.float64), 0, None))
    return EnvmapInfo(int(width), int(height), int(channels),
                      [[round(float(v), 6) for v in row] for row in sh9])
