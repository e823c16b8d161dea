"""SPZ, the open compressed Gaussian splat format (Niantic, MIT; what web splat viewers read),
written and read from its public specification: the reference implementation's
`src/cc/load-spz.cc` (nianticlabs/spz), read, then written here in numpy.

A file is gzip of: a 16-byte header (magic 0x5053474e "NGSP", version, point count, SH degree,
fractional bits, flags, a reserved byte), then per attribute for every point: positions as
24-bit signed fixed point (12 fractional bits: 1/4096 of a unit), alphas (sigmoid x 255),
colours (the SH DC coefficient x 0.15 x 255 + 127.5), log-scales ((s + 10) x 16), rotations
(version 3: the "smallest three" of the unit quaternion, 9 bits + sign each, 2 bits naming the
largest; version 2: x, y, z with w >= 0, 8 bits each), SH coefficients (coefficient-major, RGB
inner; round(128 x) + 128, degree 1 at 5 bits and the rest at 4, the reference's defaults).

Coordinates: the reference stores RUB (three.js axes) and converts from the PLY convention RDF
(3DGS) on write. We treat a frame PLY as RDF like any 3DGS PLY, so the reference's
`spz_to_ply` gives back our coordinates: y and z flip, and with them the signs of quaternion
components and SH coefficients (the reference's `coordinateConverter` table for RDF <-> RUB).

SPZ carries appearance only (one opacity, no normals or visibility); the reader fills the
geometry branch as a plain 3DGS PLY gets it (`core.plyio.read_gaussian_ply`).
"""

from __future__ import annotations

import gzip
import os
import struct
from pathlib import Path

import numpy as np

from core.export.splats import SH_REST, Splats

__all__ = ["SPZ_BOUNDS", "read_spz", "write_spz"]

MAGIC = 0x5053474E
FRACTIONAL_BITS = 12
COLOR_SCALE = 0.15
SH1_BITS, SH_REST_BITS = 5, 4  # load-spz.h DEFAULT_SH1_BITS, DEFAULT_SH_REST_BITS
_FLIP_P = np.array([1.0, -1.0, -1.0], np.float32)   # RDF <-> RUB: y and z
_FLIP_Q = np.array([1.0, -1.0, -1.0], np.float32)   # quaternion x, y, z: (y z, x z, x y)
# Per SH coefficient k = 0..14 (degrees 1..3), coordinateConverter's flipSh with x=1, y=z=-1.
_FLIP_SH = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], np.float32)
_SQRT1_2 = np.float32(0.7071067811865476)

SPZ_BOUNDS = {
    "means": 0.5 / (1 << FRACTIONAL_BITS),
    "scales": 0.5 / 16,
    "opacity": 0.5 / 255,
    "sh0": 0.5 / (COLOR_SCALE * 255),
    "sh1": 4.5 / 128,   # bucket of 8 codes: at most 4 codes off, plus rounding
    "sh_rest": 8.5 / 128,
    "quat_v3": 1.5e-3 * 2,  # 9-bit components of magnitude <= 1/sqrt(2)
    "quat_v2": 0.1,  # 8-bit x, y, z; w = sqrt(1 - |xyz|^2) is ill-conditioned where w is small
}
"""Largest round-trip error per attribute (units of the stored value; quaternions: any
component of the unit quaternion), for values inside the format's ranges."""


def _sh_dim(degree: int) -> int:
    return (degree + 1) ** 2 - 1


def _pack_quats_v3(q: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions x, y, z, w -> (N, 4) bytes, smallest three."""
    largest = np.abs(q).argmax(axis=1)
    negate = q[np.arange(len(q)), largest] < 0
    comp = largest.astype(np.uint32)
    for i in range(4):
        keep = largest != i
        neg = ((q[:, i] < 0) ^ negate).astype(np.uint32)
        mag = (np.float32(511) * (np.abs(q[:, i]) / _SQRT1_2) + np.float32(0.5)).astype(np.uint32)
        comp = np.where(keep, (comp << 10) | (neg << 9) | np.minimum(mag, 511), comp)
    return comp.astype("<u4").view(np.uint8).reshape(-1, 4)


def _unpack_quats_v3(raw: np.ndarray) -> np.ndarray:
    comp = raw.reshape(-1, 4).copy().view("<u4").reshape(-1).astype(np.uint32)
    largest = (comp >> 30).astype(np.int64)
    q = np.zeros((len(comp), 4), np.float32)
    for i in range(3, -1, -1):
        on = largest != i
        mag = (comp & 511).astype(np.float32)
        neg = ((comp >> 9) & 1).astype(bool)
        val = _SQRT1_2 * mag / np.float32(511)
        q[:, i] = np.where(on, np.where(neg, -val, val), 0)
        comp = np.where(on, comp >> 10, comp)
    rows = np.arange(len(q))
    q[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - (q * q).sum(axis=1)))
    return q


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _quantize_sh(x: np.ndarray, bits: int) -> np.ndarray:
    bucket = 1 << (8 - bits)
    q = np.rint(x * 128.0).astype(np.int32) + 128
    q = (q + bucket // 2) // bucket * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


def write_spz(path: str | os.PathLike[str], splats: Splats, *, sh_degree: int = 3,
              version: int = 3) -> int:
    """Write `splats` as SPZ (appearance only); returns the file's size in bytes."""
    if version not in (2, 3):
        raise ValueError(f"version: expected 2 or 3 (SPZ versions this writes), got {version}")
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"sh_degree: expected 0..3, got {sh_degree}")
    s = splats.canonical()
    n = len(s)
    fixed = np.rint(s.means * _FLIP_P * (1 << FRACTIONAL_BITS)).astype(np.int64)
    if n and np.abs(fixed).max() >= 1 << 23:
        raise ValueError("splats: a centre lies beyond +-2048 units, outside SPZ's 24-bit "
                         "fixed-point range; rescale the scene before exporting")
    positions = (fixed.astype("<i4").view(np.uint8).reshape(n, 3, 4)[:, :, :3]).reshape(-1)
    alphas = _to_u8(s.opacity_c * 255.0)
    colors = _to_u8(s.sh0 * (COLOR_SCALE * 255.0) + 0.5 * 255.0).reshape(-1)
    scales = _to_u8((s.scales + 10.0) * 16.0).reshape(-1)
    xyzw = np.concatenate([s.quats[:, 1:] * _FLIP_Q, s.quats[:, :1]], axis=1)
    if version == 3:
        rotations = _pack_quats_v3(xyzw).reshape(-1)
    else:
        xyzw = np.where(xyzw[:, 3:] < 0, -xyzw, xyzw)
        rotations = _to_u8(xyzw[:, :3] * 127.5 + 127.5).reshape(-1)
    dim = _sh_dim(sh_degree)
    sh = s.shN[:, :dim] * _FLIP_SH[:dim, None]
    sh_bytes = np.concatenate([_quantize_sh(sh[:, :3], SH1_BITS),
                               _quantize_sh(sh[:, 3:], SH_REST_BITS)], axis=1).reshape(-1)
    header = struct.pack("<IIIBBBB", MAGIC, version, n, sh_degree, FRACTIONAL_BITS, 0, 0)
    body = b"".join(a.tobytes() for a in (positions, alphas, colors, scales, rotations, sh_bytes))
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(gzip.compress(header + body, compresslevel=9, mtime=0))
    os.replace(tmp, path)
    return path.stat().st_size


def read_spz(path: str | os.PathLike[str]) -> Splats:
    """Read an SPZ file (versions 2 and 3; not the never-released float16 version 1)."""
    path = Path(path)
    try:
        raw = gzip.decompress(path.read_bytes())
    except (OSError, EOFError) as exc:
        raise ValueError(f"path: {path} is not an SPZ file (not gzip: {exc})") from None
    if len(raw) < 16:
        raise ValueError(f"path: {path} is not an SPZ file (no 16-byte header)")
    magic, version, n, degree, frac, _flags, _ = struct.unpack_from("<IIIBBBB", raw)
    if magic != MAGIC:
        raise ValueError(f"path: {path} is not an SPZ file (magic {magic:#x})")
    if version not in (2, 3) or degree > 3:
        raise ValueError(f"path: {path} is SPZ version {version} with SH degree {degree}; "
                         "this reads versions 2-3 up to degree 3")
    dim, rot = _sh_dim(degree), (4 if version == 3 else 3)
    sizes = [9 * n, n, 3 * n, 3 * n, rot * n, 3 * dim * n]
    if len(raw) - 16 < sum(sizes):
        raise ValueError(f"path: {path} is truncated: {n} points need {sum(sizes) + 16} bytes, "
                         f"found {len(raw)}")
    parts, at = [], 16
    for size in sizes:
        parts.append(np.frombuffer(raw, np.uint8, size, at))
        at += size
    pos, alphas, colors, scales, rotations, sh = parts
    b = pos.reshape(n, 3, 3).astype(np.int32)
    fixed = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed.astype(np.float32) / np.float32(1 << frac) * _FLIP_P
    if version == 3:
        xyzw = _unpack_quats_v3(rotations)
    else:
        xyz = rotations.reshape(n, 3).astype(np.float32) / 127.5 - 1.0
        xyzw = np.concatenate([xyz, np.sqrt(np.maximum(0, 1 - (xyz * xyz).sum(1)))[:, None]], 1)
    quats = np.concatenate([xyzw[:, 3:], xyzw[:, :3] * _FLIP_Q], axis=1)
    shN = np.zeros((n, SH_REST, 3), np.float32)
    shN[:, :dim] = (sh.reshape(n, dim, 3).astype(np.float32) - 128.0) / 128.0 * \
        _FLIP_SH[:dim, None]
    alpha = alphas.astype(np.float32) / 255.0
    return Splats(means=means, scales=scales.reshape(n, 3).astype(np.float32) / 16.0 - 10.0,
                  quats=quats, opacity_c=alpha, opacity_g=alpha.copy(),
                  sh0=(colors.reshape(n, 3).astype(np.float32) / 255.0 - 0.5) / COLOR_SCALE,
                  shN=shN, normals=np.tile(np.float32([0, 0, 1]), (n, 1)),
                  visibility=np.full(n, 0.9, np.float32),
                  ids=np.arange(n, dtype=np.int64)).canonical()
