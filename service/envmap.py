"""Environment maps clients upload for relighting: a readable OpenEXR or Radiance HDR image,
equirectangular (width = 2 x height), every pixel finite. Anything else is refused with what is
wrong, before it is stored."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["CONTENT_TYPES", "EnvmapError", "EnvmapInfo", "inspect_envmap"]

CONTENT_TYPES = {".exr": "image/x-exr", ".hdr": "image/vnd.radiance"}
HDR_MAGIC = (b"#?RADIANCE", b"#?RGBE")


class EnvmapError(ValueError):
    """The file is not a usable environment map; the message says why."""


@dataclass(frozen=True)
class EnvmapInfo:
    width: int
    height: int
    channels: int
    sh9: list[list[float]]
    """(9, 3) radiance SH in the map's own frame (poles on +z, unrotated): what the page's
    player relights with, turned into the capture's up frame and rotated there."""


def _read_exr(path: Path) -> np.ndarray:
    from core.data.images import ImageReadError, read_image

    try:
        return read_image(path)
    except ImageReadError as exc:
        raise EnvmapError(f"not a readable OpenEXR file ({exc.message})") from None


def _read_hdr(path: Path) -> np.ndarray:
    import cv2

    with open(path, "rb") as f:
        head = f.read(16)
    if not head.startswith(HDR_MAGIC):
        raise EnvmapError("not a Radiance HDR file (it must start with '#?RADIANCE')")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise EnvmapError("the Radiance HDR file cannot be decoded (truncated or corrupt?)")
    return image.reshape(image.shape[0], image.shape[1], -1)


def inspect_envmap(path: Path, suffix: str) -> EnvmapInfo:
    """Decode the whole image and check it (EnvmapError otherwise)."""
    if suffix not in CONTENT_TYPES:
        raise EnvmapError(f"unsupported file type {suffix!r}; send .exr or .hdr")
    image = _read_exr(path) if suffix == ".exr" else _read_hdr(path)
    height, width, channels = image.shape
    if channels < 3:
        raise EnvmapError(f"has {channels} channel(s); an environment map needs RGB")
    if width != 2 * height:
        raise EnvmapError(f"is {width}x{height}; an equirectangular map is twice as wide as "
                          "it is high")
    bad = int(np.count_nonzero(~np.isfinite(image[..., :3])))
    if bad:
        raise EnvmapError(f"has {bad} non-finite values (NaN or infinity)")
    from core.relight.envmap import project_sh9

    sh9 = project_sh9(np.clip(image[..., :3].astype(np.float64), 0, None))
    return EnvmapInfo(int(width), int(height), int(channels),
                      [[round(float(v), 6) for v in row] for row in sh9])
