"""Reading and writing the capture's image files (PNG, JPEG, EXR): one reader per format.

Values are returned as stored: 8/16-bit PNG and JPEG become float32 in 0..1 (still sRGB-encoded),
EXR stays linear float32. Nothing here converts colour spaces; callers that need linear light do it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["ImageReadError", "image_size", "read_image", "verify_image", "write_exr", "write_png"]


class ImageReadError(ValueError):
    """An image file is missing, of an unsupported type, or cannot be decoded."""

    def __init__(self, path: Path, message: str):
        self.path = Path(path)
        self.message = message
        super().__init__(f"{path}: {message}")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) read from the header only."""
    ext = Path(path).suffix.lower()
    if ext == ".exr":
        (x0, y0), (x1, y1) = _exr_file(path, header_only=True).header()["dataWindow"]
        return int(x1 - x0 + 1), int(y1 - y0 + 1)
    if ext in (".png", ".jpg", ".jpeg"):
        from PIL import Image

        try:
            with Image.open(path) as im:
                return im.size
        except (OSError, SyntaxError, ValueError) as exc:
            raise ImageReadError(path, f"cannot read image header: {exc}") from None
    raise ImageReadError(path, f"unsupported file type {ext!r} (expected .png, .jpg or .exr)")


def verify_image(path: Path) -> tuple[int, int, str]:
    """Decode the whole file to prove it is readable; returns (width, height, mode).

    Used by validation: a header can be intact while the pixel data is truncated, and some
    decoders silently fill the missing part, so only a strict full decode is proof.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".exr":
        arr = _read_exr(path)
        return arr.shape[1], arr.shape[0], f"F{arr.shape[2]}"
    if ext not in (".png", ".jpg", ".jpeg"):
        raise ImageReadError(path, f"unsupported file type {ext!r} (expected .png, .jpg or .exr)")
    from PIL import Image

    try:
        with Image.open(path) as im:
            im.load()
            return im.size[0], im.size[1], im.mode
    except FileNotFoundError:
        raise ImageReadError(path, "file not found") from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise ImageReadError(path, f"cannot decode image: {exc}") from None


def read_image(path: Path) -> np.ndarray:
    """Decode an image to float32 (H, W, C), C in 1..4, values as stored (see module doc)."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".exr":
        return _read_exr(path)
    if ext in (".png", ".jpg", ".jpeg"):
        return _read_ldr(path)
    raise ImageReadError(path, f"unsupported file type {ext!r} (expected .png, .jpg or .exr)")


def _read_ldr(path: Path) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise ImageReadError(path, "file not found")
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


def _exr_file(path: Path, header_only: bool = False):
    import OpenEXR

    if not Path(path).is_file():
        raise ImageReadError(path, "file not found")
    try:
        return OpenEXR.File(str(path), header_only=header_only)
    except Exception as exc:  # OpenEXR raises bare exceptions for corrupt files
        raise ImageReadError(path, f"cannot decode EXR: {exc}") from None


def _read_exr(path: Path) -> np.ndarray:
    channels = _exr_file(path).channels()
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


def write_png(path: Path, image: np.ndarray) -> None:
    """Write uint8 or uint16 (H, W) / (H, W, C) RGB(A) to PNG, creating parent folders."""
    import cv2

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
    import OpenEXR

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.ascontiguousarray(image, dtype=np.float32)
    if arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise ValueError(f"image: expected (H, W, 3|4) float, got shape {arr.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"RGB" if arr.shape[2] == 3 else "RGBA": arr}).write(str(path))
