"""A small vectorized CPU triangle rasterizer with a z-buffer (numpy).

Every (triangle, pixel-in-its-bounding-box) pair is generated at once, tested against the edge
functions at the pixel centre (u + 0.5, v + 0.5), and the nearest surviving pair per pixel wins via
one lexicographic sort. Barycentrics are perspective-correct for perspective cameras, so depth and
interpolated attributes are exact at pixel centres, which is what the ground truth needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Fragments", "interpolate", "rasterize", "rasterize_perspective"]

_MAX_PAIRS = 4_000_000  # bounds peak memory: triangles are processed in chunks of this many pairs


@dataclass(frozen=True)
class Fragments:
    """Per-pixel result of rasterization."""

    triangle: np.ndarray
    """(H, W) int64 index of the visible triangle, -1 for background."""
    bary: np.ndarray
    """(H, W, 3) float64 barycentric weights of the triangle's vertices (0 on background)."""
    depth: np.ndarray
    """(H, W) float64 depth of the visible surface (camera z or orthographic), 0 on background."""

    @property
    def mask(self) -> np.ndarray:
        return self.triangle >= 0


def rasterize(
    xy: np.ndarray, z: np.ndarray, faces: np.ndarray, width: int, height: int, *, perspective: bool
) -> Fragments:
    """Rasterize triangles given per-vertex screen positions ``xy`` (V, 2) and depths ``z`` (V,).

    ``xy`` is in continuous pixel coordinates (pixel (u, v) covers [u, u+1) x [v, v+1)). With
    ``perspective`` the barycentrics are corrected by 1/z and triangles with a vertex at z <= 0 are
    dropped; otherwise (orthographic) depth interpolates linearly.
    """
    faces = np.asarray(faces, dtype=np.int64)
    tri_xy = xy[faces]  # (T, 3, 2)
    tri_z = z[faces]
    keep = np.all(tri_z > 1e-9, axis=1) if perspective else np.ones(len(faces), bool)
    lo = np.ceil(tri_xy.min(axis=1) - 0.5)  # first pixel whose centre can be inside
    hi = np.floor(tri_xy.max(axis=1) - 0.5)
    lo = np.maximum(lo, 0).astype(np.int64)
    hi = np.minimum(hi, [width - 1, height - 1]).astype(np.int64)
    keep &= np.all(hi >= lo, axis=1)
    ids = np.nonzero(keep)[0]
    size = (hi[ids] - lo[ids] + 1).prod(axis=1)
    chunks: list[tuple[np.ndarray, ...]] = []
    start = 0
    while start < len(ids):
        stop = start + max(1, int(np.searchsorted(np.cumsum(size[start:]), _MAX_PAIRS)))
        out = _pairs(ids[start:stop], lo, hi, tri_xy, tri_z, width, perspective)
        if out is not None:
            chunks.append(out)
        start = stop
    return _resolve(chunks, width, height)


def _pairs(ids, lo, hi, tri_xy, tri_z, width, perspective):
    bw = hi[ids, 0] - lo[ids, 0] + 1
    count = bw * (hi[ids, 1] - lo[ids, 1] + 1)
    tri = np.repeat(ids, count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    bw_r = np.repeat(bw, count)
    px = lo[tri, 0] + local % bw_r
    py = lo[tri, 1] + local // bw_r
    q = np.stack([px + 0.5, py + 0.5], axis=1)
    a, b, c = tri_xy[tri, 0], tri_xy[tri, 1], tri_xy[tri, 2]
    area = _cross(b - a, c - a)
    ok = np.abs(area) > 1e-12
    area = np.where(ok, area, 1.0)
    l0 = _cross(b - q, c - q) / area
    l1 = _cross(c - q, a - q) / area
    l2 = 1.0 - l0 - l1
    inside = ok & (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
    if not inside.any():
        return None
    lam = np.stack([l0, l1, l2], axis=1)[inside]
    tri, px, py = tri[inside], px[inside], py[inside]
    zt = tri_z[tri]
    if perspective:
        w = lam / zt
        depth = 1.0 / w.sum(axis=1)
        bary = w * depth[:, None]
    else:
        bary = lam
        depth = (lam * zt).sum(axis=1)
    return py * width + px, tri, bary, depth


def _resolve(chunks: list[tuple[np.ndarray, ...]], width: int, height: int) -> Fragments:
    tri_img = np.full(height * width, -1, dtype=np.int64)
    bary_img = np.zeros((height * width, 3))
    depth_img = np.zeros(height * width)
    if chunks:
        pix, tri, bary, depth = (np.concatenate(x) for x in zip(*chunks))
        order = np.lexsort((depth, pix))  # nearest first within each pixel
        pix_s = pix[order]
        first = np.ones(len(order), bool)
        first[1:] = pix_s[1:] != pix_s[:-1]
        win = order[first]
        tri_img[pix[win]] = tri[win]
        bary_img[pix[win]] = bary[win]
        depth_img[pix[win]] = depth[win]
    return Fragments(
        tri_img.reshape(height, width),
        bary_img.reshape(height, width, 3),
        depth_img.reshape(height, width),
    )


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]


def rasterize_perspective(
    vertices: np.ndarray,
    faces: np.ndarray,
    K: np.ndarray,
    world_to_camera: np.ndarray,
    width: int,
    height: int,
) -> Fragments:
    """Rasterize a world-space mesh through a pinhole camera (OpenCV axes); depth is camera z."""
    cam = vertices @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = cam[:, 2]
    safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
    xy = np.stack(
        [K[0, 0] * cam[:, 0] / safe + K[0, 2], K[1, 1] * cam[:, 1] / safe + K[1, 2]], axis=1
    )
    return rasterize(xy, z, faces, width, height, perspective=True)


def interpolate(frags: Fragments, faces: np.ndarray, attr: np.ndarray) -> np.ndarray:
    """Interpolate per-vertex ``attr`` (V, C) to (H, W, C); background gets 0."""
    H, W = frags.triangle.shape
    out = np.zeros((H, W, attr.shape[1]))
    m = frags.mask
    corners = attr[faces[frags.triangle[m]]]  # (M, 3, C)
    out[m] = np.einsum("mk,mkc->mc", frags.bary[m], corners)
    return out
