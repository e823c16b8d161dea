"""Initial points for a capture without a point cloud: random points in the cameras' common view,
carved by the foreground masks when the capture has them (a visual hull), coloured from the
images. Also the scene extent that scales the position learning rate and densification.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from core.data.capture import Camera

__all__ = ["look_at_center", "sample_points", "scene_extent"]


def scene_extent(cameras: Sequence[Camera]) -> float:
    """1.1 x the largest distance of a camera centre from their mean (3DGS getNerfppNorm)."""
    if not cameras:
        raise ValueError("cameras: expected at least one camera")
    centers = np.stack([c.center for c in cameras])
    radius = float(np.linalg.norm(centers - centers.mean(axis=0), axis=1).max())
    return 1.1 * radius if radius > 0 else 1.0


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


def _common_radius(cameras: Sequence[Camera], center: np.ndarray) -> float:
    """Radius of a ball about `center` that every camera sees (half its narrower view at the
    centre's depth)."""
    radii = []
    for cam in cameras:
        depth = float((cam.world_to_camera[:3, :3] @ center + cam.t)[2])
        half = min(cam.width / cam.K[0, 0], cam.height / cam.K[1, 1]) / 2
        radii.append(max(depth, 1e-6) * half)
    return float(min(radii))


def sample_points(cameras: Sequence[Camera], n: int, *, images: Sequence[np.ndarray] | None = None,
                  masks: Sequence[np.ndarray | None] | None = None, seed: int = 0,
                  max_rounds: int = 50) -> tuple[torch.Tensor, torch.Tensor]:
    """Up to `n` points (n, 3) and colours (n, 3) inside the cube about the cameras' look-at centre
    that every camera sees; with masks (H, W, 1) a point must land on foreground (> 0.5) in every
    camera. Colours: mean of `images` (H, W, 3) at the projections (grey without images)."""
    if n < 1:
        raise ValueError(f"n: expected >= 1, got {n}")
    if images is not None and len(images) != len(cameras):
        raise ValueError(f"images: expected {len(cameras)} images, got {len(images)}")
    if masks is not None and len(masks) != len(cameras):
        raise ValueError(f"masks: expected {len(cameras)} masks, got {len(masks)}")
    rng = np.random.default_rng(seed)
    center = look_at_center(cameras)
    r = _common_radius(cameras, center)
    kept: list[np.ndarray] = []
    total = 0
    for _ in range(max_rounds):
        pts = center + rng.uniform(-r, r, size=(4 * n, 3))
        ok = np.ones(len(pts), dtype=bool)
        for i, cam in enumerate(cameras):
            uv, z = cam.project(pts)
            u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
            inside = (z > 0) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
            ok &= inside
            if masks is not None and masks[i] is not None:
                m = masks[i][np.clip(v, 0, cam.height - 1), np.clip(u, 0, cam.width - 1), 0]
                ok &= m > 0.5
        kept.append(pts[ok])
        total += int(ok.sum())
        if total >= n:
            break
    pts = np.concatenate(kept)[:n]
    if len(pts) == 0:
        raise ValueError("masks: no point lands on foreground in every camera; check the masks")
    return torch.from_numpy(pts).float(), torch.from_numpy(_colours(cameras, pts, images)).float()


def _colours(cameras: Sequence[Camera], pts: np.ndarray,
             images: Sequence[np.ndarray] | None) -> np.ndarray:
    if images is None:
        return np.full((len(pts), 3), 0.5)
    acc = np.zeros((len(pts), 3))
    for cam, img in zip(cameras, images):
        uv, _ = cam.project(pts)
        u = np.clip(np.floor(uv[:, 0]).astype(int), 0, cam.width - 1)
        v = np.clip(np.floor(uv[:, 1]).astype(int), 0, cam.height - 1)
        acc += img[v, u, :3]
    return np.clip(acc / len(cameras), 0.0, 1.0)
