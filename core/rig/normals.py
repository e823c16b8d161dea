"""Normal priors from fused depth: at each pixel the plane fitted (least squares, the smallest
principal axis) to the fused points of the (2 r + 1)^2 window about it, facing the camera.
Its confidence is the share of the window with fused depth times how planar the points are
(1 - their surface variation / `MAX_VARIATION`, Pauly et al. 2002): flat panels get confident
priors, edges and clutter none. A pixel without depth of its own still gets the plane of a
window mostly covered (small holes are filled).

Numpy and OpenCV only; world-space normals (OpenCV axes for the camera)."""

from __future__ import annotations

import cv2
import numpy as np

from core.data.capture import Camera

__all__ = ["MAX_VARIATION", "depth_normals", "resize_prior"]

MAX_VARIATION = 0.05
"""Surface variation lambda_0 / (lambda_0 + lambda_1 + lambda_2) at which the confidence reaches
0 (a plane: 0; points spread evenly in a ball: 1/3)."""
MIN_COVER = 0.5
"""Share of the window that must have depth for a plane to be fitted."""


def _sums(a: np.ndarray, size: int) -> np.ndarray:
    return cv2.boxFilter(a, cv2.CV_64F, (size, size), normalize=False,
                         borderType=cv2.BORDER_CONSTANT)


def depth_normals(camera: Camera, depth: np.ndarray, radius: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """World normals (H, W, 3) float32 (zero where none) and confidence (H, W) float32 in 0..1
    of an (H, W) depth map (0: unknown), planes fitted over (2 radius + 1)^2 windows."""
    h, w = depth.shape
    size = 2 * radius + 1
    valid = (depth > 0).astype(np.float64)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x = (u + 0.5 - camera.K[0, 2]) / camera.K[0, 0]
    y = (v + 0.5 - camera.K[1, 2]) / camera.K[1, 1]
    pts = np.stack([x * depth, y * depth, depth.astype(np.float64)], axis=-1) * valid[..., None]
    count = _sums(valid, size)
    fit = count >= MIN_COVER * size * size
    normals = np.zeros((h, w, 3), np.float32)
    confidence = np.zeros((h, w), np.float32)
    if not fit.any():
        return normals, confidence
    n = count[fit][:, None]
    mean = np.stack([_sums(pts[..., i], size)[fit] for i in range(3)], axis=1) / n
    cov = np.empty((len(n), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            s = _sums(pts[..., i] * pts[..., j], size)[fit] / n[:, 0]
            cov[:, i, j] = cov[:, j, i] = s - mean[:, i] * mean[:, j]
    values, vectors = np.linalg.eigh(cov)  # ascending eigenvalues
    normal = vectors[:, :, 0]
    # Face the camera: the normal points back along the ray to the window's centre.
    flip = np.einsum("ij,ij->i", normal, mean) > 0
    normal[flip] *= -1
    variation = values[:, 0] / np.maximum(values.sum(axis=1), 1e-30)
    planar = np.clip(1.0 - variation / MAX_VARIATION, 0.0, 1.0)
    normals[fit] = (normal @ camera.R).astype(np.float32)  # camera to world: n_w = R^T n_c
    confidence[fit] = (planar * np.clip(n[:, 0] / (size * size), 0, 1)).astype(np.float32)
    normals[confidence <= 0] = 0.0
    return normals, confidence


def resize_prior(normals: np.ndarray, confidence: np.ndarray, width: int, height: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A prior computed on reduced views brought to (width, height): bilinear, renormalised."""
    if normals.shape[:2] == (height, width):
        return normals, confidence
    n = cv2.resize(normals, (width, height), interpolation=cv2.INTER_LINEAR)
    c = cv2.resize(confidence, (width, height), interpolation=cv2.INTER_LINEAR)
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    n = np.where(norm > 0.5, n / np.maximum(norm, 1e-6), 0.0).astype(np.float32)
    return n, np.where(norm[..., 0] > 0.5, c, 0.0).astype(np.float32)
