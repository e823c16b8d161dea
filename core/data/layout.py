"""Where a calibrated rig looks: the point its optical axes meet, the ball every camera sees
about it (seeding, meshing and the rig's stereo start from these), and the near plane its
renders clip at (`TrainConfig.near`). Torch-free: a run is resolved with it."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from core.data.capture import Camera

__all__ = ["NEAR_FRACTION", "common_radius", "look_at_center", "near_plane"]

NEAR_FRACTION = 0.2
"""The near plane of a rig's renders, as a fraction of its median camera distance to the point
the cameras look at: in a dome, Gaussians of the wall beside or just in front of a camera
project huge at the rasterizer's 0.01 and smear its view, and large faint ones a few tenths in
front of a held-out camera, which no training view sees from there, haze all of it. A fifth:
the Panoptic twin's training views fuse nothing nearer than 0.42 of that distance (a key frame
says when a capture's stereo finds a surface within twice the plane) (docs/decisions/
2026-11-29-seeds-and-priors-from-the-rig.md)."""


def look_at_center(cameras: Sequence[Camera]) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cameras:
        d = cam.R[2] / np.linalg.norm(cam.R[2])  # optical axis (camera +z) in world
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
    if np.linalg.matrix_rank(A) < 3:  # parallel axes: fall back to a point in front of them
        return np.mean([c.center + c.R[2] for c in cameras], axis=0)
    return np.linalg.solve(A, b)


def common_radius(cameras: Sequence[Camera], center: np.ndarray) -> float:
    """Radius of a ball about `center` that every camera sees (half its narrower view at the
    centre's depth)."""
    radii = []
    for cam in cameras:
        depth = float((cam.world_to_camera[:3, :3] @ center + cam.t)[2])
        half = min(cam.width / cam.K[0, 0], cam.height / cam.K[1, 1]) / 2
        radii.append(max(depth, 1e-6) * half)
    return float(min(radii))


def near_plane(cameras: Sequence[Camera], fraction: float = NEAR_FRACTION) -> float:
    """The near plane (camera depth) of renders of a rig: `fraction` of the median distance
    from the cameras' centres to the point they look at (`look_at_center`), at most twice the
    median distance from their centroid: axes that barely meet (a forward-facing rig) put
    that point far beyond the scene, while a dome's or a ring's spread is about its radius."""
    if not cameras:
        raise ValueError("cameras: expected at least one camera")
    if not 0 < fraction < 1:
        raise ValueError(f"fraction: expected 0 < fraction < 1, got {fraction}")
    centers = np.array([c.center for c in cameras])
    distance = float(np.median(np.linalg.norm(centers - look_at_center(cameras), axis=1)))
    spread = float(np.median(np.linalg.norm(centers - centers.mean(axis=0), axis=1)))
    if spread > 0:
        distance = min(distance, 2.0 * spread)
    if not np.isfinite(distance) or distance <= 0:
        raise ValueError("cameras: their centres all sit on the point they look at; give "
                         "train.near")
    return fraction * distance
