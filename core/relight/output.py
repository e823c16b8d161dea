"""Writing relit views: sRGB PNG (clipped, composited on the run's background), linear EXR
(premultiplied RGBA, the OpenEXR convention) and H.264 MP4.

MP4s are H.264 (libx264) in yuv420p with the moov atom first (+faststart), what browsers play;
yuv420p needs even sizes, so odd frames are padded by one row/column of edge pixels. The ffmpeg
binary is the one imageio-ffmpeg ships (no system ffmpeg needed).
"""

from __future__ import annotations

from pathlib import Path

import imageio_ffmpeg
import numpy as np

from core.data.images import write_exr, write_png

__all__ = ["Mp4Writer", "read_mp4_info", "to_uint8", "write_views"]


def to_uint8(x: np.ndarray) -> np.ndarray:
    return (np.clip(x, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_views(stem: Path, srgb: np.ndarray, linear_rgba: np.ndarray) -> list[Path]:
    """stem.png (sRGB (H, W, 3) in 0..1) and stem.exr (linear premultiplied (H, W, 4))."""
    png, exr = stem.with_suffix(".png"), stem.with_suffix(".exr")
    write_png(png, to_uint8(srgb))
    write_exr(exr, linear_rgba.astype(np.float32))
    return [png, exr]


class Mp4Writer:
    """Frames (H, W, 3) uint8 sRGB in, an H.264 yuv420p MP4 out; use as a context manager."""

    def __init__(self, path: Path, width: int, height: int, fps: float = 24.0, crf: int = 18):
        if not fps > 0:
            raise ValueError(f"fps: expected > 0, got {fps}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.size = (width + width % 2, height + height % 2)
        self.frames = 0
        self._gen = imageio_ffmpeg.write_frames(
            str(self.path), self.size, fps=fps, codec="libx264", pix_fmt_in="rgb24",
            pix_fmt_out="yuv420p", quality=None, macro_block_size=1, ffmpeg_log_level="error",
            output_params=["-crf", str(crf), "-movflags", "+faststart"])
        self._gen.send(None)

    def write(self, frame: np.ndarray) -> None:
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
            raise ValueError(f"frame: expected (H, W, 3) uint8, got {frame.dtype} {frame.shape}")
        w, h = self.size
        pad = ((0, h - frame.shape[0]), (0, w - frame.shape[1]), (0, 0))
        if pad[0][1] < 0 or pad[1][1] < 0:
            raise ValueError(f"frame: expected at most {w}x{h}, got {frame.shape[1]}x"
                             f"{frame.shape[0]}")
        self._gen.send(np.ascontiguousarray(np.pad(frame, pad, mode="edge")))
        self.frames += 1

    def close(self) -> None:
        if self._gen is not None:
            self._gen.close()
            self._gen = None

    def __enter__(self) -> Mp4Writer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_mp4_info(path: Path) -> dict:
    """{"frames", "width", "height", "codec", "pix_fmt"} of a video, by decoding it fully."""
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = reader.__next__()
    count = sum(1 for _ in reader)
    codec = str(meta.get("codec", ""))
    return {"frames": count, "width": meta["size"][0], "height": meta["size"][1],
            "codec": codec, "pix_fmt": str(meta.get("pix_fmt", ""))}
