"""Where a calibrated rig looks: the point its optical axes meet, and the ball every camera sees
about it (seeding, meshing and the rig's stereo all start from these)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from core.data.capture import Camera

__all__ = ["common_radius", "look_at_center"]


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
