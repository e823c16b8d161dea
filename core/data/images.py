"""Reading and writing image files (PNG, JPEG, EXR, Radiance HDR): one reader per format, each
behind a header check (core.data.headers: format, size, pixel limit) so nothing is decoded that
should not be.

Values are returned as stored: 8/16-bit PNG and JPEG become float32 in 0..1 (still sRGB-encoded),
EXR stays linear float32. Nothing here converts colour spaces; callers that need linear light do it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import OpenEXR
from PIL import JpegImagePlugin, PngImagePlugin

from core.data.headers import HeaderError, ImageHeader, check_pixels, read_header

__all__ = ["ImageReadError", "image_size", "read_image", "verify_image", "write_exr", "write_png"]


class ImageReadError(ValueError):
    """An image file is missing, of an unsupported type, too large, or cannot be decoded.

    `message` never contains a path: `path` says which file, and a caller that knows the file
    by another name (capture-relative, an asset's name) uses `named` to say it that way."""

    def __init__(self, path: Path | str, message: str):
        self.path = Path(path)
        self.message = message
        super().__init__(f"{path}: {message}")

    def named(self, name: str) -> ImageReadError:
        """The same error, naming the file `name`."""
        return ImageReadError(name, self.message)


def _header(path: Path, max_pixels: int | None, *, limit: bool = True) -> ImageHeader:
    try:
        header = read_header(path)
        if limit:
            check_pixels(header, max_pixels)
    except HeaderError as exc:
        raise ImageReadError(path, str(exc)) from None
    return header


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) read from the header only (no pixel limit: nothing is decoded)."""
    header = _header(Path(path), None, limit=False)
    return header.width, header.height


def verify_image(path: Path, max_pixels: int | None = None) -> tuple[int, int, str]:
    """Decode the whole file to prove it is readable; returns (width, height, mode).

    The header is read first: an empty, truncated or wrong-format file, or one of more than
    `max_pixels` pixels (default: the process's, core.data.headers), is refused before any
    decoding. Used by validation: a header can be intact while the pixel data is truncated, and
    some decoders silently fill the missing part, so only a strict full decode is proof.
    """
    path = Path(path)
    header = _header(path, max_pixels)
    if header.format in ("exr", "hdr"):
        arr = _DECODERS[header.format](path)
        return arr.shape[1], arr.shape[0], f"F{arr.shape[2]}"

    # The plugin classes, not Image.open: the header check above is the pixel limit, and
    # Image.open would add PIL's own (a fixed 179 MP) on top of the configured one.
    kind = PngImagePlugin.PngImageFile if header.format == "png" else \
        JpegImagePlugin.JpegImageFile
    try:
        with open(path, "rb") as f, kind(f) as im:
            im.load()
            return im.size[0], im.size[1], im.mode
    except (OSError, SyntaxError, ValueError, EOFError) as exc:
        raise ImageReadError(path, f"cannot decode image: {_clean(exc, path)}") from None


def read_image(path: Path, max_pixels: int | None = None) -> np.ndarray:
    """Decode an image to float32 (H, W, C), C in 1..4, values as stored (see module doc);
    the header is checked first as in `verify_image`."""
    path = Path(path)
    header = _header(path, max_pixels)
    return _DECODERS[header.format](path)


def _clean(exc: BaseException, path: Path) -> str:
    """A library's message without the file's path (some name it)."""
    return str(exc).replace(str(path), path.name) or type(exc).__name__


def _read_ldr(path: Path) -> np.ndarray:
    # cv2 keeps 16-bit PNGs at full precision, which PIL does not for RGB.
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ImageReadError(path, "cannot decode image (corrupt or truncated?)")
    if raw.ndim == 2:
        raw = raw[:, :, None]
    elif raw.shape[2] == 3:
        raw = raw[:, :, ::-1]
    elif raw.shape[2] == 4:
        raw = raw[:, :, [2, 1, 0, 3]]
    if raw.dtype == np.uint8:
        return raw.astype(np.float32) / 255.0
    if raw.dtype == np.uint16:
        return raw.astype(np.float32) / 65535.0
    return raw.astype(np.float32)


def _read_hdr(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ImageReadError(path, "cannot decode the Radiance HDR pixels (truncated or "
                                   "corrupt?)")
    image = image.reshape(image.shape[0], image.shape[1], -1).astype(np.float32)
    return np.ascontiguousarray(image[..., [2, 1, 0]]) if image.shape[2] >= 3 else image


def _read_exr(path: Path) -> np.ndarray:
    try:
        channels = OpenEXR.File(str(path)).channels()
    except Exception:  # OpenEXR raises bare exceptions (naming the path) for corrupt data
        raise ImageReadError(path, "cannot decode the OpenEXR pixels (truncated or "
                                   "corrupt?)") from None
    for key in ("RGBA", "RGB"):
        if key in channels:
            return np.ascontiguousarray(channels[key].pixels, dtype=np.float32)
    names = [n for n in ("R", "G", "B", "A", "Y") if n in channels]
    if not names:
        names = sorted(channels)
    planes = [np.asarray(channels[n].pixels, dtype=np.float32) for n in names]
    if not planes or any(p.ndim != 2 for p in planes):
        raise ImageReadError(path, f"EXR has no usable channels ({sorted(channels)})")
    return np.stack(planes, axis=2)


_DECODERS = {"png": _read_ldr, "jpeg": _read_ldr, "exr": _read_exr, "hdr": _read_hdr}


def write_png(path: Path, image: np.ndarray) -> None:
    """Write uint8 or uint16 (H, W) / (H, W, C) RGB(A) to PNG, creating parent folders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.asarray(image)
    if arr.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"image: expected uint8 or uint16, got {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim == 3 and arr.shape[2] == 3:
        arr = arr[:, :, ::-1]
    elif arr.ndim == 3 and arr.shape[2] == 4:
        arr = arr[:, :, [2, 1, 0, 3]]
    if not cv2.imwrite(str(path), np.ascontiguousarray(arr)):
        raise OSError(f"{path}: cannot write PNG")


def write_exr(path: Path, image: np.ndarray) -> None:
    """Write float (H, W, 3) or (H, W, 4) to a ZIP-compressed float32 EXR."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.ascontiguousarray(image, dtype=np.float32)
    if arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise ValueError(f"image: expected (H, W, 3|4) float, got shape {arr.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"RGB" if arr.shape[2] == 3 else "RGBA": arr}).write(str(path))
