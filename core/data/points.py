"""Point clouds that seed training: the canonical capture's optional ``points.ply`` and the
sources importers convert into it (COLMAP ``points3D``, a nerfstudio ``ply_file_path``).

``points.ply`` holds world points (the capture's world, like ``world_to_camera``) with optional
8-bit colours; it seeds every key frame (docs/capture-format.md). Readers raise ``ValueError``
naming the file and what is wrong; this module must not import torch (the API validates with it).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "POINTS_PLY",
    "PointCloud",
    "read_colmap_points",
    "read_points_ply",
    "write_colmap_points",
    "write_points_ply",
]

POINTS_PLY = "points.ply"

_PLY_TYPES = {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "uchar": "u1",
              "uint8": "u1", "char": "i1", "int8": "i1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4",
              "uint32": "u4"}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


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


def _header(path: Path, raw: bytes) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]],
                                             int]:
    """(format, [(element, count, [(property, type)])], data offset)."""
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' / 'end_header' lines)")
    offset = raw.index(b"\n", end) + 1 if b"\n" in raw[end:] else len(raw)
    fmt, elements = None, []
    for line in raw[:end].decode("ascii", errors="replace").splitlines()[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format" and len(parts) >= 2:
            fmt = parts[1]
        elif parts[0] == "element" and len(parts) == 3 and parts[2].isdigit():
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property" and elements:
            kind = "list" if parts[1] == "list" else parts[1]
            elements[-1][2].append((parts[-1], kind))
        else:
            raise ValueError(f"{path}: cannot read PLY header line {line!r}")
    if fmt not in _FORMATS:
        raise ValueError(f"{path}: PLY format {fmt!r} is not ascii or binary_*_endian")
    return fmt, elements, offset


def read_points_ply(path: str | os.PathLike[str]) -> PointCloud:
    """Vertices of a PLY file (ascii or binary): x, y, z and, when present, red, green, blue
    (8-bit, or floats in 0..1). Other properties and elements are ignored."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc.strerror}") from None
    fmt, elements, offset = _header(path, raw)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise ValueError(f"{path}: no 'vertex' element")
    _, count, props = elements[names.index("vertex")]
    if any(kind == "list" for _, kind in props):
        raise ValueError(f"{path}: list properties on vertices are not supported")
    unknown = [kind for _, kind in props if kind not in _PLY_TYPES]
    if unknown:
        raise ValueError(f"{path}: unsupported property type {unknown[0]!r}")
    fields = [name for name, _ in props]
    if not {"x", "y", "z"} <= set(fields):
        raise ValueError(f"{path}: vertices need x, y and z properties, got {fields}")
    if fmt == "ascii":
        rows = raw[offset:].decode("ascii", errors="replace").splitlines()
        skip = sum(c for e, c, _ in elements[:names.index("vertex")])
        try:
            table = np.array([r.split()[:len(fields)] for r in rows[skip:skip + count]], float)
        except ValueError:
            raise ValueError(f"{path}: a vertex line is not numeric") from None
        if table.shape != (count, len(fields)):
            raise ValueError(f"{path}: expected {count} vertex lines of {len(fields)} numbers")
        column = {name: table[:, i] for i, name in enumerate(fields)}
    else:
        if names.index("vertex") != 0:
            raise ValueError(f"{path}: in binary files the vertices must come first")
        dtype = np.dtype([(n, _FORMATS[fmt] + _PLY_TYPES[k]) for n, k in props])
        if len(raw) - offset < count * dtype.itemsize:
            raise ValueError(f"{path}: truncated: {count} vertices need {count * dtype.itemsize} "
                             f"bytes, found {len(raw) - offset}")
        data = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
        column = {name: data[name] for name in fields}
    points = np.stack([column[k].astype(np.float64) for k in "xyz"], axis=1)
    if not np.isfinite(points).all():
        raise ValueError(f"{path}: vertex coordinates contain NaN or Inf")
    colors = None
    if {"red", "green", "blue"} <= set(fields):
        # Integer colours are 8-bit (0..255), float ones already 0..1.
        scale = 1.0 if dict(props)["red"] in ("float", "float32", "double", "float64") else 255.0
        colors = np.clip(np.stack([column[k] for k in ("red", "green", "blue")], axis=1)
                         / scale, 0, 1).astype(np.float32)
    return PointCloud(points, colors)


def write_points_ply(path: str | os.PathLike[str], cloud: PointCloud) -> None:
    """Binary little-endian PLY: float x y z, uchar red green blue (grey without colours),
    written atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rec = np.empty(len(cloud), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                      ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, k in enumerate("xyz"):
        rec[k] = cloud.points[:, i]
    colors = cloud.colors if cloud.colors is not None else np.full((len(cloud), 3), 0.5)
    rgb = np.clip(np.round(colors * 255), 0, 255).astype(np.uint8)
    for i, k in enumerate(("red", "green", "blue")):
        rec[k] = rgb[:, i]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(cloud)}",
              "property float x", "property float y", "property float z",
              "property uchar red", "property uchar green", "property uchar blue", "end_header"]
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(("\n".join(header) + "\n").encode("ascii") + rec.tobytes())
    os.replace(tmp, path)


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
