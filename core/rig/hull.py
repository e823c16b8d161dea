"""Normals of the visual hull (Laurentini 1994) where the views have mattes: a voxel grid over
the subject carved by every matte (a voxel survives where it lands on the foreground of every
view it falls in, and at least two views see it), its occupancy smoothed, and each view's
normal the smoothed occupancy's outward gradient at the hull's surface voxel nearest the camera
along the pixel's ray. At the silhouette the hull's normal is exact (the ray grazes it); inside
it, the hull holds a convex shape where stereo finds no texture, as a subject's limbs and
flanks often are at low resolution.

Numpy and SciPy only."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage

from core.data.capture import Camera

__all__ = ["HULL_CONFIDENCE", "hull_normals"]

HULL_CONFIDENCE = 0.5
"""The confidence a hull normal gets (stereo's plane fits reach 1)."""
SMOOTH = 1.5
"""Voxels of the Gaussian that smooths the occupancy before its gradient is taken."""


def _project(cam: Camera, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer pixel (u, v) and depth of float32 points (N, 3) in an ideal pinhole: one matrix
    product (a grid has millions of voxels)."""
    P = (cam.K @ cam.world_to_camera[:3]).astype(np.float32)
    uvw = pts @ P[:, :3].T + P[:, 3]
    z = uvw[:, 2]
    safe = np.where(z > 1e-9, z, 1e-9)
    return (np.floor(uvw[:, 0] / safe).astype(np.int64),
            np.floor(uvw[:, 1] / safe).astype(np.int64), z)


def _carve(cameras: Sequence[Camera], masks: Sequence[np.ndarray], lo: np.ndarray,
           hi: np.ndarray, n: int, min_seen: int = 2
           ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Occupancy (n, n, n) of the grid over the box [lo, hi] (voxels seen by at least
    `min_seen` views), its voxel centres and size, and which voxels a matte carved (a view saw
    them on its background)."""
    size = float((hi - lo).max() / n)
    axes = [lo[i] + (np.arange(n) + 0.5) * size for i in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    centres = centres.astype(np.float32)
    alive = np.arange(len(centres))  # each view projects only what the ones before kept
    seen = np.zeros(len(centres), np.int16)
    carved = np.zeros(len(centres), bool)
    for cam, mask in zip(cameras, masks):
        u, v, z = _project(cam, centres[alive])
        inside = (z > 0) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
        fg = np.zeros(len(alive), bool)
        fg[inside] = mask[v[inside], u[inside], 0] > 0.5
        seen[alive] += inside
        carved[alive[inside & ~fg]] = True
        alive = alive[~inside | fg]
    occ = np.zeros(len(centres), bool)
    occ[alive] = seen[alive] >= min_seen
    return occ.reshape(n, n, n), centres.reshape(n, n, n, 3), size, carved.reshape(n, n, n)


def _box(cameras: Sequence[Camera], masks: Sequence[np.ndarray], center: np.ndarray,
         radius: float, n: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The hull's bounding box, two voxels wider, from a coarse carve of the cube about
    `center` that keeps what three quarters of the views see (a voxel that few views see
    is carved by few: far from the subject, their cones meet in large phantom volumes);
    None when nothing survives. Each matte is grown by a coarse voxel's footprint at the
    subject's distance first: a voxel is kept where any of it may be foreground, so a part
    thinner than a voxel (a neck, a raised arm) does not cut the box short."""
    lo, hi = center - radius, center + radius
    size = 2 * radius / n
    grown = []
    for cam, mask in zip(cameras, masks):
        reach = int(np.ceil(0.87 * cam.K[0, 0] * size / max(
            float(np.linalg.norm(cam.center - center)), 1e-9)))
        grown.append(ndimage.maximum_filter(mask[..., 0], size=2 * reach + 1)[..., None])
    occ, centres, size, _ = _carve(cameras, grown, lo, hi, n,
                                   max(2, int(np.ceil(0.75 * len(cameras)))))
    if not occ.any():
        return None
    pts = centres[occ]
    return pts.min(axis=0) - 2 * size, pts.max(axis=0) + 2 * size


def hull_normals(cameras: Sequence[Camera], masks: Sequence[np.ndarray], center: np.ndarray,
                 radius: float, resolution: int = 128
                 ) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """Per view the hull's world normals (H, W, 3) float32 (zero off the hull) and a confidence
    (H, W) float32 (`HULL_CONFIDENCE` on it): mattes (H, W, 1), the subject inside the cube
    `center` +- `radius`; None when the mattes carve everything away."""
    box = _box(cameras, masks, center, radius, max(16, resolution // 4))
    if box is None:
        return None
    occ, centres, size, carved = _carve(cameras, masks, *box, resolution,
                                        max(2, int(np.ceil(0.75 * len(cameras)))))
    if not occ.any():
        return None
    smooth = ndimage.gaussian_filter(occ.astype(np.float32), SMOOTH)
    grad = np.stack(np.gradient(smooth), axis=-1)
    surface = occ & ~ndimage.binary_erosion(occ)
    pts, nrm = centres[surface], -grad[surface]
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    # The subject's surface is where a matte carved the voxel beside it. Where the hull ends
    # because too few views saw past it (a head out of frame in a quarter of the views) or at
    # the grid's edge, it is cut flat, not the subject: those voxels still hide what is behind
    # them, with no normal.
    nrm[~ndimage.binary_dilation(carved, np.ones((3, 3, 3), bool))[surface]] = 0.0
    return [_draw(cam, pts, nrm, size) for cam in cameras]


def _draw(cam: Camera, pts: np.ndarray, nrm: np.ndarray, size: float
          ) -> tuple[np.ndarray, np.ndarray]:
    """The nearest surface voxel's normal at each pixel, each voxel covering the pixels of its
    footprint (a voxel wider than a pixel leaves no gap for the far side to show through)."""
    u, v, z = _project(cam, pts)
    ok = np.flatnonzero(z > 0)
    reach = 0 if not len(ok) else int(np.floor(0.5 * cam.K[0, 0] * size / z[ok].min() + 0.5))
    us, vs, zs, ids = [], [], [], []
    for dv in range(-reach, reach + 1):
        for du in range(-reach, reach + 1):
            us.append(u[ok] + du)
            vs.append(v[ok] + dv)
            zs.append(z[ok])
            ids.append(ok)
    u, v, z, ids = (np.concatenate(a) for a in (us, vs, zs, ids))
    inside = (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
    u, v, z, ids = u[inside], v[inside], z[inside], ids[inside]
    pixel = v * cam.width + u
    order = np.lexsort((z, pixel))  # by pixel, nearest first
    first = order[np.r_[True, pixel[order][1:] != pixel[order][:-1]]] if len(order) else order
    normals = np.zeros((cam.height * cam.width, 3), np.float32)
    normals[pixel[first]] = nrm[ids[first]]
    normals = normals.reshape(cam.height, cam.width, 3)
    confidence = np.where(np.linalg.norm(normals, axis=2) > 0.5, HULL_CONFIDENCE,
                          0.0).astype(np.float32)
    return normals, confidence
