"""Malformed files for the decoder tests (core and API): each format truncated, with the wrong
magic bytes, empty, with no pixels, and with huge dimensions. The huge ones are headers written
by hand (a few dozen bytes), never 400 MP of pixels."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

HUGE = (20000, 20000)
"""400 MP: over the default pixel limit (core.data.headers.DEFAULT_MAX_PIXELS)."""
EXTS = {"png": ".png", "jpeg": ".jpg", "exr": ".exr", "hdr": ".hdr"}


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(
        ">I", zlib.crc32(kind + data))


def png_header(width: int, height: int) -> bytes:
    """Signature, IHDR (8-bit RGB) and an IDAT of nothing: what a header reader sees."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(b""))


def jpeg_header(width: int, height: int) -> bytes:
    """SOI and a baseline frame header (SOF0, 3 components) and nothing after."""
    sof = struct.pack(">BHHB", 8, height, width, 3) + b"\x01\x11\x00\x02\x11\x00\x03\x11\x00"
    return b"\xff\xd8\xff\xc0" + struct.pack(">H", len(sof) + 2) + sof


def hdr_header(width: int, height: int) -> bytes:
    return (b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y %d +X %d\n" % (height, width)
            + b"\x02\x02\x00\x08")


def exr_with_window(good: bytes, width: int, height: int) -> bytes:
    """A real EXR whose dataWindow is rewritten to `width` x `height` (box2i: 4 int32)."""
    key = b"dataWindow\x00box2i\x00"
    at = good.index(key) + len(key) + 4
    return good[:at] + struct.pack("<4i", 0, 0, width - 1, height - 1) + good[at + 16:]


def good_image(fmt: str, folder: Path, width: int = 64, height: int = 32) -> bytes:
    """A valid file of `fmt`, RGB, large enough that half of it cuts into the pixel data."""
    import cv2

    rng = np.random.default_rng(1)
    path = folder / f"good{EXTS[fmt]}"
    if fmt == "exr":
        from core.data.images import write_exr

        write_exr(path, rng.random((height, width, 3), dtype=np.float32) + 0.1)
    elif fmt == "hdr":
        assert cv2.imwrite(str(path), rng.random((height, width, 3), dtype=np.float32) + 0.1)
    else:
        assert cv2.imwrite(str(path), rng.integers(0, 255, (height, width, 3), np.uint8))
    return path.read_bytes()


def bad_variants(fmt: str, good: bytes) -> dict[str, tuple[bytes, str]]:
    """name -> (bytes, words the error must contain) for a file of `fmt`."""
    header = {"png": png_header, "jpeg": jpeg_header, "hdr": hdr_header,
              "exr": lambda w, h: exr_with_window(good, w, h)}[fmt]
    huge, zero = header(*HUGE), header(0, 0)
    return {
        "truncated header": (good[:12], "truncated"),
        "truncated pixels": (good[:len(good) * 2 // 3], "truncated"),
        "wrong magic": (b"GIF89a" + good[6:], "magic" if fmt != "hdr" else "#?RADIANCE"),
        "empty": (b"", "empty (0 bytes)"),
        "no pixels": (zero, "no pixels" if fmt != "exr" else "corrupt OpenEXR header"),
        "huge": (huge, f"is {HUGE[0]}x{HUGE[1]}"),
    }


def bmp_header(width: int, height: int) -> bytes:
    """BITMAPFILEHEADER and BITMAPINFOHEADER of a 24-bit BMP, no pixels."""
    info = struct.pack("<IiiHHIIiiII", 40, width, height, 1, 24, 0, 0, 2835, 2835, 0, 0)
    return b"BM" + struct.pack("<IHHI", 14 + 40, 0, 0, 54) + info
