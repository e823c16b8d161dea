"""Image headers read before anything is decoded: the format (by extension, checked against the
file's magic bytes) and the size, refused when a file is empty, truncated before its size is
known, zero-sized or larger than a pixel limit. A decoder given a 20000 x 20000 PNG would try to
allocate gigabytes; its header says so in 24 bytes.

Messages never contain the path (callers name the file the way their user knows it).
"""

from __future__ import annotations

import importlib
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import OpenEXR

__all__ = [
    "DEFAULT_MAX_PIXELS",
    "FORMATS",
    "HeaderError",
    "ImageHeader",
    "check_pixels",
    "default_max_pixels",
    "read_header",
    "read_other_header",
    "set_default_max_pixels",
]

ImageFormat = Literal["png", "jpeg", "exr", "hdr"]
FORMATS: dict[str, ImageFormat] = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg",
                                   ".exr": "exr", ".hdr": "hdr"}
DEFAULT_MAX_PIXELS = 150_000_000
"""Largest image decoded unless configured otherwise: a 16384 x 8192 environment map (134 MP)
passes, a 20000 x 20000 image (400 MP, 4.8 GB as float32 RGB) does not."""

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_EXR_MAGIC = b"v/1\x01"
_HDR_MAGIC = (b"#?RADIANCE", b"#?RGBE")
_HDR_HEADER_BYTES = 64 * 1024
# Radiance resolution string: "-Y <height> +X <width>" for the usual top-down scanlines; the
# other seven orientations swap or flip the axes (Ward, "Real Pixels", Graphics Gems II).
_HDR_RESOLUTION = re.compile(rb"^([-+])([XY]) (\d{1,9}) ([-+])([XY]) (\d{1,9})$")
_limit = [DEFAULT_MAX_PIXELS]


class HeaderError(ValueError):
    """The header is missing, of the wrong format, truncated, or names an unusable size."""


@dataclass(frozen=True)
class ImageHeader:
    width: int
    height: int
    format: ImageFormat

    @property
    def pixels(self) -> int:
        return self.width * self.height


def set_default_max_pixels(limit: int) -> None:
    """The pixel limit of this process's reads that pass none (a worker sets its setting)."""
    if limit < 1:
        raise ValueError(f"limit: expected a positive number of pixels, got {limit}")
    _limit[0] = int(limit)


def default_max_pixels() -> int:
    return _limit[0]


def check_pixels(header: ImageHeader, max_pixels: int | None = None) -> None:
    """HeaderError when the image has more pixels than `max_pixels` (default: the process's)."""
    limit = max_pixels if max_pixels is not None else _limit[0]
    if header.pixels > limit:
        raise HeaderError(f"is {header.width}x{header.height} ({header.pixels} pixels); the "
                          f"limit is {limit} pixels")


def read_header(path: Path) -> ImageHeader:
    """The image's format and size from its header alone (HeaderError otherwise); the format
    comes from the extension and must match the file's content."""
    path = Path(path)
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise HeaderError(f"unsupported file type {path.suffix or '(none)'!r} (expected "
                          ".png, .jpg, .exr or .hdr)")
    try:
        size = path.stat().st_size
        if size == 0:
            raise HeaderError("is empty (0 bytes)")
        width, height = _READERS[fmt](path)
    except FileNotFoundError:
        raise HeaderError("file not found") from None
    except OSError as exc:  # a folder, a file that cannot be opened: never its path
        raise HeaderError(f"cannot be read ({exc.strerror or type(exc).__name__})") from None
    if width <= 0 or height <= 0:
        raise HeaderError(f"has no pixels (its header says {width}x{height})")
    return ImageHeader(width, height, fmt)


def _png(path: Path) -> tuple[int, int]:
    # PNG 1.2 (ISO 15948) 5.2-5.3: the signature, then IHDR, whose data opens with width and
    # height as big-endian uint32.
    with open(path, "rb") as f:
        head = f.read(24)
    if not head.startswith(_PNG_MAGIC[:len(head)]) or len(head) >= 8 and \
            head[:8] != _PNG_MAGIC:
        raise HeaderError("is not a PNG file (wrong magic bytes)")
    if len(head) < 24:
        raise HeaderError(f"is truncated: {len(head)} bytes, too few for a PNG header")
    if head[12:16] != b"IHDR":
        raise HeaderError("is not a valid PNG file (its first chunk is not IHDR)")
    return struct.unpack(">II", head[16:24])


def _jpeg(path: Path) -> tuple[int, int]:
    # ITU T.81 B.1.1: after SOI, marker segments (0xFF, code, big-endian length that counts
    # itself) up to the frame header SOFn, whose data is precision, height, width.
    with open(path, "rb") as f:
        if f.read(2) != b"\xff\xd8":
            raise HeaderError("is not a JPEG file (wrong magic bytes)")
        while True:
            head = f.read(2)
            while len(head) == 2 and head[0] == 0xFF and head[1] == 0xFF:  # fill bytes
                head = head[1:] + f.read(1)
            if len(head) < 2 or head[0] != 0xFF:
                raise HeaderError("has a truncated or corrupt JPEG header (no frame header)")
            code = head[1]
            if code == 0x01 or 0xD0 <= code <= 0xD7:  # markers without a segment
                continue
            if code in (0xD9, 0xDA):
                raise HeaderError("is not a valid JPEG file (no frame header before its data)")
            size = f.read(2)
            if len(size) < 2 or struct.unpack(">H", size)[0] < 2:
                raise HeaderError("has a truncated or corrupt JPEG header")
            body = struct.unpack(">H", size)[0] - 2
            if 0xC0 <= code <= 0xCF and code not in (0xC4, 0xC8, 0xCC):  # SOFn
                frame = f.read(5)
                if len(frame) < 5:
                    raise HeaderError("has a truncated JPEG frame header")
                height, width = struct.unpack(">HH", frame[1:5])
                return width, height
            f.seek(body, 1)


def _exr(path: Path) -> tuple[int, int]:
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != _EXR_MAGIC:
        raise HeaderError("is not an OpenEXR file (wrong magic bytes)")
    try:
        header = OpenEXR.File(str(path), header_only=True).header()
        (x0, y0), (x1, y1) = header["dataWindow"]
    except Exception:  # OpenEXR raises bare RuntimeErrors that name the path
        raise HeaderError("has a truncated or corrupt OpenEXR header") from None
    return int(x1) - int(x0) + 1, int(y1) - int(y0) + 1


def _hdr(path: Path) -> tuple[int, int]:
    with open(path, "rb") as f:
        head = f.read(_HDR_HEADER_BYTES)
    if not head.startswith(_HDR_MAGIC):
        raise HeaderError("is not a Radiance HDR file (it must start with '#?RADIANCE')")
    end = head.find(b"\n\n")
    if end < 0:
        raise HeaderError("has a truncated Radiance HDR header (no blank line ends it)")
    line, newline, _ = head[end + 2:].partition(b"\n")
    match = _HDR_RESOLUTION.match(line.strip()) if newline else None
    if match is None or match[2] == match[5]:
        raise HeaderError("has no valid resolution line after its header (e.g. '-Y 512 "
                          "+X 1024')")
    first, second = int(match[3]), int(match[6])
    return (second, first) if match[2] == b"Y" else (first, second)


_READERS = {"png": _png, "jpeg": _jpeg, "exr": _exr, "hdr": _hdr}
_OTHER = {".bmp": ("BmpImagePlugin", "BmpImageFile"), ".tif": ("TiffImagePlugin", "TiffImageFile"),
          ".tiff": ("TiffImagePlugin", "TiffImageFile"), ".webp": ("WebPImagePlugin",
                                                                  "WebPImageFile"),
          ".ppm": ("PpmImagePlugin", "PpmImageFile"), ".pgm": ("PpmImagePlugin", "PpmImageFile")}


def read_other_header(path: Path) -> tuple[int, int]:
    """(width, height) of an image importers convert to PNG (BMP, TIFF, WebP, PPM/PGM), from
    its header (HeaderError otherwise)."""
    path = Path(path)
    where = _OTHER.get(path.suffix.lower())
    if where is None:
        raise HeaderError(f"unsupported file type {path.suffix or '(none)'!r}")
    kind = getattr(importlib.import_module(f"PIL.{where[0]}"), where[1])
    try:
        # The plugin's constructor parses the header only and decodes nothing (Image.open
        # would add PIL's own pixel limit, which the setting replaces).
        with open(path, "rb") as f, kind(f) as im:
            width, height = im.size
    except FileNotFoundError:
        raise HeaderError("file not found") from None
    except (OSError, SyntaxError, ValueError, EOFError, struct.error) as exc:
        raise HeaderError(f"has a truncated or corrupt {path.suffix[1:].upper()} header "
                          f"({exc})") from None
    if width <= 0 or height <= 0:
        raise HeaderError(f"has no pixels (its header says {width}x{height})")
    return width, height
