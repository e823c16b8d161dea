"""A key frame's depth from its calibrated views: each view reduced to `max_side`, swept against
its chosen sources (`core.rig.stereo`), the depths fused across views (`core.rig.fusion`)."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from core.config.rig import StereoConfig
from core.data.capture import Camera
from core.rig.fusion import Fused, fuse
from core.rig.stereo import DepthMap, choose_sources, depth_range, grey, plane_sweep, reduced

__all__ = ["rig_depth"]


def _fallback_range(cameras: Sequence[Camera]) -> tuple[float, float, float]:
    """Depths that hold anything the rig can see when no scene point says more: from a
    twentieth of the rig's span to twice it, typically half of it."""
    centers = np.stack([c.center for c in cameras])
    span = float(np.linalg.norm(centers - centers.mean(axis=0), axis=1).max()) * 2
    span = span if span > 0 else 1.0
    return 0.05 * span, 2.0 * span, 0.5 * span


def rig_depth(cameras: Sequence[Camera], images: Sequence[np.ndarray],
              masks: Sequence[np.ndarray | None] | None = None,
              points: np.ndarray | None = None,
              config: StereoConfig = StereoConfig()) -> Fused:
    """Every view's fused depth: cameras (ideal pinholes) with their images (H, W, 3) in 0..1;
    `masks` (H, W, 1), where given, restrict a view's depth to their foreground; `points`
    (N, 3) sparse scene points set each view's depth range. The result is at the reduced
    resolution (`StereoConfig.max_side`): its cameras say which."""
    if len(images) != len(cameras):
        raise ValueError(f"images: expected {len(cameras)} images, got {len(images)}")
    masks = list(masks) if masks is not None else [None] * len(cameras)
    if len(masks) != len(cameras):
        raise ValueError(f"masks: expected {len(cameras)} masks, got {len(masks)}")
    small = [reduced(c, np.asarray(im, np.float32), config.max_side)
             for c, im in zip(cameras, images)]
    cams = [c for c, _ in small]
    rgb = [im for _, im in small]
    greys = [grey(im) for im in rgb]
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64)
    fallback = _fallback_range(cameras)
    maps = []
    for i, cam in enumerate(cams):
        near, far, typical = depth_range(cam, pts, fallback)
        sources = choose_sources(cams, i, typical, config)
        mask = None
        if masks[i] is not None:
            mask = cv2.resize(np.asarray(masks[i], np.float32)[..., 0], (cam.width, cam.height),
                              interpolation=cv2.INTER_AREA)
        if not sources:
            maps.append(DepthMap(cam, np.zeros((cam.height, cam.width), np.float32),
                                 np.full((cam.height, cam.width), 2.0, np.float32)))
            continue
        maps.append(plane_sweep(cam, greys[i], [(cams[j], greys[j]) for j in sources], near,
                                far, config, mask))
    return fuse(maps, rgb, config)
