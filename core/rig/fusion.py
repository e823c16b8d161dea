"""Depth maps fused across views with a geometric consistency check (as multi-view stereo
pipelines fuse, e.g. COLMAP's stereo fusion and MVSNet's filter): a pixel's point survives
where at least `min_views` other views agree with it. Another view agrees when the point
projects inside it in front, its depth there is within `depth_tolerance` of the point's, and
its own point there projects back within `reprojection` pixels of the pixel. A surviving
point is the mean of the agreeing views' points, coloured by the mean of their pixels.

Numpy only; cameras ideal pinholes, depths camera z (0: unknown)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from core.config.rig import StereoConfig
from core.data.capture import Camera
from core.data.points import PointCloud
from core.rig.stereo import DepthMap

__all__ = ["Fused", "backproject", "fuse"]


@dataclass
class Fused:
    """Depth maps after the consistency check, and the fused points."""

    cameras: list[Camera]
    depths: list[np.ndarray]
    """Per view (H, W) float32 depth of the fused point where it survived, 0 elsewhere."""
    support: list[np.ndarray]
    """Per view (H, W) int16 how many other views agree (0 where it did not survive)."""
    cloud: PointCloud
    """Every surviving pixel's fused point and colour, view by view."""
    view: np.ndarray
    """(N,) which view each point of `cloud` came from."""


def backproject(camera: Camera, depth: np.ndarray, where: np.ndarray | None = None
                ) -> np.ndarray:
    """World points (N, 3) of the pixels `where` (H, W) bool (default: depth > 0) of an (H, W)
    depth map, in row-major order."""
    if where is None:
        where = depth > 0
    v, u = np.nonzero(where)
    z = depth[v, u].astype(np.float64)
    rays = np.linalg.solve(camera.K, np.stack([u + 0.5, v + 0.5, np.ones_like(z)]))
    cam = (rays * z).T
    return (cam - camera.t) @ camera.R


def _lookup(camera: Camera, depth: np.ndarray, points: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For world points (N, 3): their depth in `camera`, the integer pixel they fall in, and
    whether that pixel is inside and has a depth."""
    uv, z = camera.project(points)
    u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    h, w = depth.shape
    inside = (z > 0) & (u >= 0) & (v >= 0) & (u < w) & (v < h)
    uc, vc = np.clip(u, 0, w - 1), np.clip(v, 0, h - 1)
    return z, uc, vc, inside & (depth[vc, uc] > 0)


def _agreement(ref: Camera, pix: np.ndarray, pts: np.ndarray, other: Camera,
               depth: np.ndarray, config: StereoConfig) -> tuple[np.ndarray, np.ndarray]:
    """Whether `other` agrees with each of the reference's points `pts` (N, 3) seen at pixels
    `pix` (N, 2) of `ref`, and its point for each (N, 3)."""
    z, u, v, ok = _lookup(other, depth, pts)
    theirs = depth[v, u].astype(np.float64)
    ok &= np.abs(theirs - z) <= config.depth_tolerance * np.maximum(z, 1e-12)
    back = np.zeros_like(pts)
    if ok.any():
        rays = np.linalg.solve(other.K, np.stack([u[ok] + 0.5, v[ok] + 0.5,
                                                  np.ones(int(ok.sum()))]))
        back[ok] = ((rays * theirs[ok]).T - other.t) @ other.R
        uv, zb = ref.project(back[ok])
        err = np.linalg.norm(uv - (pix[ok] + 0.5), axis=1)
        good = (zb > 0) & (err <= config.reprojection)
        ok[np.flatnonzero(ok)[~good]] = False
    return ok, back


def fuse(maps: Sequence[DepthMap], images: Sequence[np.ndarray],
         config: StereoConfig = StereoConfig()) -> Fused:
    """The consistency check over every pair of views (module docstring); `images` (H, W, 3)
    in 0..1 at each depth map's resolution colour the points."""
    if len(images) != len(maps):
        raise ValueError(f"images: expected {len(maps)} images, got {len(images)}")
    depths, support, points, colors, view = [], [], [], [], []
    for i, m in enumerate(maps):
        where = m.depth > 0
        v, u = np.nonzero(where)
        pts = backproject(m.camera, m.depth, where)
        pix = np.stack([u, v], axis=1).astype(np.float64)
        count = np.zeros(len(pts), np.int16)
        acc, col = pts.copy(), images[i][v, u, :3].astype(np.float64)
        for j, other in enumerate(maps):
            if j == i or not len(pts):
                continue
            ok, back = _agreement(m.camera, pix, pts, other.camera, other.depth, config)
            count += ok
            acc[ok] += back[ok]
            _, uo, vo, _ = _lookup(other.camera, other.depth, back[ok])
            col[ok] += images[j][vo, uo, :3]
        keep = count >= config.min_views
        n = (count[keep] + 1.0)[:, None]
        mean = acc[keep] / n
        kept = np.zeros_like(m.depth)
        # the fused (mean) point's depth: the agreeing views average the matching noise away
        kept[v[keep], u[keep]] = (mean @ m.camera.R[2] + m.camera.t[2]).astype(np.float32)
        sup = np.zeros(m.depth.shape, np.int16)
        sup[v[keep], u[keep]] = count[keep]
        depths.append(kept)
        support.append(sup)
        points.append(mean)
        colors.append(col[keep] / n)
        view.append(np.full(int(keep.sum()), i, np.int32))
    cloud = PointCloud(np.concatenate(points) if points else np.zeros((0, 3)),
                       np.clip(np.concatenate(colors), 0, 1).astype(np.float32)
                       if colors else np.zeros((0, 3), np.float32))
    return Fused([m.camera for m in maps], depths, support, cloud,
                 np.concatenate(view) if view else np.zeros(0, np.int32))
