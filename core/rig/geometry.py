"""`RigGeometry`: what a key frame's calibrated views give without a point cloud, each part
computed once on first use and timed: sparse points triangulated from the known poses
(`core.triangulation`), every view's depth fused across views (`core.rig.depth`), and normal
priors with confidences from that depth (`core.rig.normals`)."""

from __future__ import annotations

import time
from collections.abc import Sequence

import cv2
import numpy as np

from core.config.rig import StereoConfig
from core.data.capture import Camera
from core.data.layout import look_at_center
from core.data.points import PointCloud
from core.rig.depth import rig_depth
from core.rig.fusion import Fused
from core.rig.hull import hull_normals
from core.rig.normals import depth_normals, resize_prior
from core.triangulation import TriangulationStats, triangulate_views

__all__ = ["RigGeometry"]


class RigGeometry:
    """The views of one key frame: cameras served at the images' resolution, images (H, W, 3)
    in 0..1, mattes (H, W, 1) or None (they restrict features, depth and points to the
    foreground), and `depth_masks` that restrict the depth alone (a later key frame's subject,
    `core.seeding`). `threads` caps OpenCV's threads while it computes (the run's torch
    threads: a one-thread benchmark stays on one core)."""

    def __init__(self, cameras: Sequence[Camera], images: Sequence[np.ndarray],
                 masks: Sequence[np.ndarray | None], config: StereoConfig = StereoConfig(), *,
                 depth_masks: Sequence[np.ndarray | None] | None = None, threads: int = 0):
        if not len(images) == len(masks) == len(cameras):
            raise ValueError(f"images, masks: expected {len(cameras)} of each, got "
                             f"{len(images)} and {len(masks)}")
        self.cameras, self.images, self.masks = list(cameras), list(images), list(masks)
        self.depth_masks = list(depth_masks) if depth_masks is not None else self.masks
        self.config, self.threads = config, threads
        self.seconds: dict[str, float] = {}
        """Seconds each part took: triangulation, stereo (depth and fusion), priors."""
        self._sparse: tuple[PointCloud, TriangulationStats] | None = None
        self._fused: Fused | None = None

    def _timed(self, part: str, work):
        previous = cv2.getNumThreads()
        if self.threads:
            cv2.setNumThreads(self.threads)
        start = time.perf_counter()
        try:
            return work()
        finally:
            self.seconds[part] = self.seconds.get(part, 0.0) + time.perf_counter() - start
            cv2.setNumThreads(previous)

    def sparse(self) -> tuple[PointCloud, TriangulationStats]:
        """Points triangulated from the known poses (carved by the mattes) and their counts."""
        if self._sparse is None:
            self._sparse = self._timed("triangulation", lambda: triangulate_views(
                self.cameras, self.images, self.masks))
        return self._sparse

    def fused(self) -> Fused:
        """Every view's depth fused across views (at `StereoConfig.max_side`), its depth range
        from the sparse points."""
        if self._fused is None:
            points = self.sparse()[0].points
            self._fused = self._timed("stereo", lambda: rig_depth(
                self.cameras, self.images, self.depth_masks, points, self.config))
        return self._fused

    def priors(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per view a world-space normal prior (H, W, 3) float32 (zero: none), its confidence
        (H, W, 1) float32 in 0..1 and where it was measured (H, W, 1) float32 (1: a plane
        fitted to the fused depth; 0: elsewhere, where every view has a matte the visual
        hull's normals fill what stereo left, `core.rig.hull`), at the view's resolution."""
        fused = self.fused()

        def work():
            out = []
            for cam, small, depth in zip(self.cameras, fused.cameras, fused.depths):
                n, c = depth_normals(small, depth, self.config.normal_radius)
                out.append(resize_prior(n, c, cam.width, cam.height))
            hull = self._hull()
            measured = [c > 0 for _, c in out]
            if hull is not None:
                out = [(np.where(c[..., None] > 0, n, hn), np.where(c > 0, c, hc))
                       for (n, c), (hn, hc) in zip(out, hull)]
            return [(n.astype(np.float32), c[..., None].astype(np.float32),
                     m[..., None].astype(np.float32)) for (n, c), m in zip(out, measured)]
        return self._timed("priors", work)

    def _hull(self) -> list[tuple[np.ndarray, np.ndarray]] | None:
        if not self.masks or any(m is None for m in self.masks):
            return None
        center = look_at_center(self.cameras)
        reach = max(float(np.linalg.norm(c.center - center)) for c in self.cameras)
        return hull_normals(self.cameras, self.masks, center, reach)

    def nearest(self, share: float = 1.0) -> float | None:
        """The nearest surface any view's fused depth holds: per view the `share` percentile
        of its fused depths (a few stray pixels do not count), the least over the views; None
        before `fused` ran (it is not run for this) or where no depth survived."""
        if self._fused is None:
            return None
        near = [float(np.percentile(d[d > 0], share)) for d in self._fused.depths
                if np.any(d > 0)]
        return min(near) if near else None

    def note(self) -> str:
        """One line for the run's notes: what was computed and how long it took."""
        parts = ", ".join(f"{k} {v:.1f} s" for k, v in self.seconds.items())
        return f"rig geometry from {len(self.cameras)} views: {parts}"
