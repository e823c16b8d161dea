"""Point clouds that seed training: the canonical capture's optional ``points.ply`` and the
sources importers convert into it (COLMAP ``points3D``, a nerfstudio ``ply_file_path``).

``points.ply`` holds world points (the capture's world, like ``world_to_camera``) with optional
8-bit colours; it seeds every key frame (docs/capture-format.md). The PLY files themselves are
read and written by `core.plyio`. Readers raise ``ValueError`` naming the file and what is
wrong; this module must not import torch (the API validates with it).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.plyio import read_point_ply, write_point_ply

__all__ = [
    "POINTS_PLY",
    "PointCloud",
    "read_colmap_points",
    "read_points_ply",
    "write_colmap_points",
    "write_points_ply",
]

POINTS_PLY = "points.ply"


@dataclass(frozen=True)
class PointCloud:
    """World points with optional colours."""

    points: np.ndarray
    """(N, 3) float64 world coordinates."""
    colors: np.ndarray | None = None
    """(N, 3) float32 sRGB colours in 0..1, or None."""

    def __post_init__(self) -> None:
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"points: expected shape (N, 3), got {self.points.shape}")
        if self.colors is not None and self.colors.shape != self.points.shape:
            raise ValueError(f"colors: expected shape {self.points.shape}, got "
                             f"{self.colors.shape}")

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def subset(self, keep: np.ndarray) -> PointCloud:
        """The points selected by a boolean mask or index array."""
        return PointCloud(self.points[keep], None if self.colors is None else self.colors[keep])


def read_points_ply(path: str | os.PathLike[str]) -> PointCloud:
    """Vertices of a PLY file (ascii or binary): x, y, z and, when present, red, green, blue
    (8-bit, or floats in 0..1). Other properties and elements are ignored."""
    return PointCloud(*read_point_ply(path))


def write_points_ply(path: str | os.PathLike[str], cloud: PointCloud) -> None:
    """Binary little-endian PLY: float x y z, uchar red green blue (grey without colours),
    written atomically."""
    write_point_ply(path, cloud.points, cloud.colors)


def read_colmap_points(model: str | os.PathLike[str]) -> PointCloud | None:
    """COLMAP's ``points3D.txt`` or ``.bin`` in `model` (None when absent or empty): X Y Z and
    R G B of every point; tracks and errors are not needed to seed."""
    model = Path(model)
    txt, binary = model / "points3D.txt", model / "points3D.bin"
    if txt.is_file():
        pts, cols = [], []
        for i, line in enumerate(txt.read_text(errors="replace").splitlines()):
            if not line.strip() or line.startswith("#"):
                continue
            f = line.split()
            try:
                pts.append([float(x) for x in f[1:4]])
                cols.append([int(x) for x in f[4:7]])
            except (ValueError, IndexError):
                raise ValueError(f"{txt}: line {i + 1} is not 'ID X Y Z R G B ...'") from None
            if len(pts[-1]) != 3 or len(cols[-1]) != 3:
                raise ValueError(f"{txt}: line {i + 1} is not 'ID X Y Z R G B ...'")
    elif binary.is_file():
        pts, cols = _read_points_bin(binary)
    else:
        return None
    if not pts:
        return None
    points = np.asarray(pts, dtype=np.float64)
    if not np.isfinite(points).all():
        raise ValueError(f"{txt if txt.is_file() else binary}: coordinates contain NaN or Inf")
    return PointCloud(points, (np.asarray(cols, dtype=np.float32) / 255.0).clip(0, 1))


def _read_points_bin(path: Path) -> tuple[list, list]:
    raw = path.read_bytes()
    pts, cols, at = [], [], 8
    try:
        (n,) = struct.unpack_from("<Q", raw, 0)
        for _ in range(n):
            _, x, y, z, r, g, b, _err, track = struct.unpack_from("<Q3d3BdQ", raw, at)
            at += struct.calcsize("<Q3d3BdQ") + 8 * track
            if at > len(raw):
                raise struct.error("past the end")
            pts.append([x, y, z])
            cols.append([r, g, b])
    except struct.error:
        raise ValueError(f"{path}: ends early (truncated?)") from None
    return pts, cols


def write_colmap_points(model: str | os.PathLike[str], cloud: PointCloud | None, *,
                        binary: bool = False) -> Path:
    """``points3D.txt`` / ``.bin`` in `model` with empty tracks and zero errors (what an export
    without image observations can say)."""
    model = Path(model)
    cloud = cloud if cloud is not None else PointCloud(np.zeros((0, 3)))
    colors = cloud.colors if cloud.colors is not None else np.full((len(cloud), 3), 0.5)
    rgb = np.clip(np.round(colors * 255), 0, 255).astype(int)
    if binary:
        path = model / "points3D.bin"
        chunks = [struct.pack("<Q", len(cloud))]
        chunks += [struct.pack("<Q3d3BdQ", i + 1, *p, *c, 0.0, 0)
                   for i, (p, c) in enumerate(zip(cloud.points.tolist(), rgb.tolist()))]
        path.write_bytes(b"".join(chunks))
        return path
    path = model / "points3D.txt"
    lines = ["# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]"]
    lines += [f"{i + 1} {p[0]!r} {p[1]!r} {p[2]!r} {c[0]} {c[1]} {c[2]} 0.0"
              for i, (p, c) in enumerate(zip(cloud.points.tolist(), rgb.tolist()))]
    path.write_text("\n".join(lines) + "\n")
    return path
