"""Per-view depth from a calibrated rig: a plane sweep over the known poses (Collins 1996;
Gallup et al. 2007, as multi-view stereo pipelines start).

For a reference view, each of `StereoConfig.planes` fronto-parallel planes (evenly spaced in
inverse depth over the view's depth range) maps every neighbouring source view onto it by a
homography; the cost of a depth at a pixel is 1 - the normalised cross-correlation of the grey
windows, averaged over the best `best` sources (a surface hidden from one neighbour still
matches in the others). The depth is the lowest cost's, refined between planes by a parabola,
and kept where that cost is low and the window has texture. Sources are chosen by baseline and
angle: their rays meet the view's at its scene depth between `min_angle` and `max_angle`,
nearest `target_angle` first, and they look the same way.

Numpy and OpenCV only (no torch); images in 0..1, cameras ideal pinholes (undistorted).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from core.config.rig import StereoConfig
from core.data.capture import Camera

__all__ = ["DepthMap", "choose_sources", "depth_range", "grey", "plane_sweep", "reduced",
           "sweep_planes"]

# Inverse-depth range margins around the scene's points: a surface just outside them is still
# swept.
NEAR_MARGIN, FAR_MARGIN = 0.7, 1.5


@dataclass
class DepthMap:
    """A view's depth (H, W) float32 camera z, 0 where unknown, and its matching cost there."""

    camera: Camera
    depth: np.ndarray
    cost: np.ndarray


def grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 luma of an (H, W, 3) image in 0..1."""
    rgb = np.asarray(image[..., :3], np.float32)
    return np.ascontiguousarray(rgb @ np.array([0.299, 0.587, 0.114], np.float32))


def reduced(camera: Camera, image: np.ndarray, max_side: int) -> tuple[Camera, np.ndarray]:
    """The camera and image reduced (area averaging) so the longer side is at most `max_side`."""
    scale = max(camera.width, camera.height) / max_side
    if scale <= 1:
        return camera, image
    w, h = max(1, round(camera.width / scale)), max(1, round(camera.height / scale))
    small = cv2.resize(np.ascontiguousarray(image, np.float32), (w, h),
                       interpolation=cv2.INTER_AREA)
    return camera.scaled(w, h), small.reshape(h, w, *image.shape[2:])


def _axis(cam: Camera) -> np.ndarray:
    return cam.R[2] / np.linalg.norm(cam.R[2])


def choose_sources(cameras: Sequence[Camera], index: int, depth: float,
                   config: StereoConfig) -> list[int]:
    """Up to `config.sources` cameras to match view `index` with: its point at `depth` along
    the optical axis falls inside them, their rays meet there at an angle within
    [min_angle, max_angle] (nearest `target_angle` first), and their axes are within 90 degrees
    of its own."""
    ref = cameras[index]
    x = ref.center + depth * _axis(ref)
    to_ref = ref.center - x
    scored = []
    for j, cam in enumerate(cameras):
        if j == index or float(_axis(cam) @ _axis(ref)) <= 0:
            continue
        uv, z = cam.project(x[None])
        if z[0] <= 0 or not (0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height):
            continue
        to_src = cam.center - x
        cos = float(to_ref @ to_src) / max(np.linalg.norm(to_ref) * np.linalg.norm(to_src),
                                           1e-12)
        angle = math.degrees(math.acos(min(1.0, max(-1.0, cos))))
        if config.min_angle <= angle <= config.max_angle:
            scored.append((abs(angle - config.target_angle), j))
    return [j for _, j in sorted(scored)[:config.sources]]


def depth_range(camera: Camera, points: np.ndarray, fallback: tuple[float, float, float]
                ) -> tuple[float, float, float]:
    """(near, far, typical) camera depths of the scene `points` (N, 3) the camera sees: the 2nd
    and 98th percentiles with margins (near at least a tenth of the median), and the median;
    `fallback` when it sees fewer than 8."""
    if len(points):
        uv, z = camera.project(points)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < camera.width) & \
            (uv[:, 1] < camera.height)
        if inside.sum() >= 8:
            near, mid, far = np.percentile(z[inside], [2, 50, 98])
            return (max(float(near) * NEAR_MARGIN, 0.1 * float(mid)), float(far) * FAR_MARGIN,
                    float(mid))
    return fallback


_Z = np.array([0.0, 0.0, 1.0])
_HALF = np.array([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1.0]])  # index -> our +0.5 centres
_HALF_INV = np.linalg.inv(_HALF)


def _pixel_homography(ref: Camera, src: Camera, depth: float) -> np.ndarray:
    """H mapping a reference pixel index (centre at integers, as OpenCV counts) to the source
    pixel index that sees the point of the fronto-parallel plane z = `depth` through it."""
    R = src.R @ ref.R.T
    t = src.t - R @ ref.t
    H = src.K @ (R + np.outer(t, _Z) / depth) @ np.linalg.inv(ref.K)
    return _HALF_INV @ H @ _HALF


def _box(a: np.ndarray, size: int) -> np.ndarray:
    return cv2.boxFilter(a, cv2.CV_32F, (size, size), normalize=True,
                         borderType=cv2.BORDER_REFLECT)


# Outside the source a warped pixel takes this value; a window's mean below 0 then says that it
# sampled outside (the pictures are in 0..1), without a second warp to say where.
OUTSIDE = -100.0


def _source_cost(ref: np.ndarray, ref_mean: np.ndarray, ref_var: np.ndarray, src: np.ndarray,
                 H: np.ndarray, size: int) -> np.ndarray:
    """(H, W) 1 - NCC of the reference windows and the source warped by H, 2 where the window
    leaves the source or the plane is behind it."""
    h, w = ref.shape
    warped = cv2.warpPerspective(src, H, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=OUTSIDE)
    mean = _box(warped, size)
    var = _box(warped * warped, size) - mean * mean
    cross = _box(warped * ref, size) - mean * ref_mean
    cost = 1.0 - cross / np.sqrt(np.maximum(var * ref_var, 1e-10))
    np.clip(cost, 0.0, 2.0, out=cost)
    cost[mean < 0] = 2.0
    behind = _behind(H, (h, w))
    if behind is not None:
        cost[behind] = 2.0
    return cost


def _behind(H: np.ndarray, shape: tuple[int, int]) -> np.ndarray | None:
    """Where the homography's points are behind the source (the third coordinate of H x, up to
    a positive factor the source depth, is not positive); None when nowhere (it is linear in
    the pixel, so the corners tell)."""
    h, w = shape
    corners = H[2, 0] * np.array([0, w, 0, w]) + H[2, 1] * np.array([0, 0, h, h]) + H[2, 2]
    if (corners > 0).all():
        return None
    v, u = np.mgrid[0:h, 0:w]
    return (H[2, 0] * u + H[2, 1] * v + H[2, 2]) <= 0


def _best_mean(costs: Sequence[np.ndarray], best: int) -> np.ndarray:
    """The mean of the `best` lowest of the (H, W) costs, pixel by pixel (running minima: a sort
    along a short axis is far slower)."""
    low = [np.full_like(costs[0], np.inf) for _ in range(best)]
    for c in costs:
        for k in range(best):
            smaller = np.minimum(low[k], c)
            c = np.maximum(low[k], c)
            low[k] = smaller
    return sum(low[1:], low[0]) / best


def sweep_planes(ref: Camera, src: Camera, near: float, far: float, limit: int) -> int:
    """Planes enough that neighbouring ones move the reference's central ray in the source by
    about a pixel, between 16 and `limit`."""
    ray = np.linalg.solve(ref.K, np.array([ref.width / 2, ref.height / 2, 1.0]))
    pts = np.stack([ray * near, ray * far]) - ref.t
    uv, _ = src.project(pts @ ref.R)
    return int(np.clip(np.ceil(np.linalg.norm(uv[1] - uv[0])), 16, limit))


def plane_sweep(ref_cam: Camera, ref_image: np.ndarray, sources: Sequence[tuple[Camera,
                np.ndarray]], near: float, far: float, config: StereoConfig,
                mask: np.ndarray | None = None) -> DepthMap:
    """The depth of every pixel of `ref_image` (H, W) grey in 0..1 from `sources` [(camera, grey
    image)] between `near` and `far` (module docstring); `mask` (H, W) restricts it (> 0.5)."""
    if not 0 < near < far:
        raise ValueError(f"near, far: expected 0 < near < far, got {near}, {far}")
    if not sources:
        raise ValueError("sources: expected at least one source view")
    h, w = ref_image.shape
    size = config.window | 1
    ref = np.ascontiguousarray(ref_image, np.float32)
    ref_mean = _box(ref, size)
    ref_var = np.maximum(_box(ref * ref, size) - ref_mean * ref_mean, 0.0)
    planes = max(sweep_planes(ref_cam, cam, near, far, config.planes) for cam, _ in sources)
    inv = np.linspace(1.0 / near, 1.0 / far, planes)
    best = min(config.best, len(sources))
    track = _Minimum((h, w))
    for d, depth in enumerate(1.0 / inv):
        track.add(d, _best_mean([_source_cost(ref, ref_mean, ref_var, img,
                                              _pixel_homography(ref_cam, cam, float(depth)), size)
                                 for cam, img in sources], best))
    return _select(ref_cam, track, inv, ref_var, config, mask)


class _Minimum:
    """The running lowest cost over the planes, pixel by pixel, with its plane and the costs of
    the planes either side (for the parabola): the cost volume is never held whole."""

    def __init__(self, shape: tuple[int, int]):
        self.cost = np.full(shape, np.inf, np.float32)
        self.before = np.full(shape, np.inf, np.float32)
        self.after = np.full(shape, np.inf, np.float32)
        self.plane = np.zeros(shape, np.int32)
        self.last: np.ndarray | None = None

    def add(self, d: int, cost: np.ndarray) -> None:
        # the best so far is the plane just before this one: this is its cost after
        np.copyto(self.after, cost, where=self.plane == d - 1)
        lower = cost < self.cost
        np.copyto(self.cost, cost, where=lower)
        np.copyto(self.plane, d, where=lower)
        np.copyto(self.before, np.inf if self.last is None else self.last, where=lower)
        np.copyto(self.after, np.inf, where=lower)
        self.last = cost


def _select(camera: Camera, track: _Minimum, inv: np.ndarray, ref_var: np.ndarray,
            config: StereoConfig, mask: np.ndarray | None) -> DepthMap:
    """The lowest cost's depth per pixel, refined by a parabola through its neighbours in
    inverse depth; 0 where the cost is high, the window flat, or the best plane the first or
    last (the surface may lie outside the range)."""
    k, c0, cm, cp = track.plane, track.cost, track.before, track.after
    inner = (k > 0) & (k < len(inv) - 1)
    curve = np.where(inner, cm - 2 * c0 + cp, 0.0)
    offset = np.where(curve > 1e-6, 0.5 * (cm - cp) / np.maximum(curve, 1e-6), 0.0)
    step = inv[1] - inv[0]
    inv_depth = inv[k] + np.clip(offset, -0.5, 0.5) * step
    ok = inner & (c0 < config.max_cost) & (ref_var >= config.min_texture ** 2)
    if mask is not None:
        ok &= mask > 0.5
    depth = np.where(ok, 1.0 / np.maximum(inv_depth, 1e-12), 0.0).astype(np.float32)
    return DepthMap(camera, depth, np.where(ok, c0, 2.0).astype(np.float32))
