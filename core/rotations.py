"""Quaternions and rotation matrices in numpy, on `scipy.spatial.transform.Rotation`: the one
conversion for everything that does not need gradients (COLMAP poses, glTF nodes, the stream
codec). Training's differentiable version is `native.reference.quat_to_rotmat` (torch).

Quaternions here are scalar-first, w, x, y, z, as in 3DGS, COLMAP and glTF's matrices (glTF
itself stores x, y, z, w; scipy too, which is why every call below says `scalar_first`).
Torch-free (the API imports COLMAP captures with it).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["quat_to_rotmat", "rotmat_to_quat"]


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions w, x, y, z of any norm -> (..., 3, 3) float64 rotation matrices (a
    zero quaternion gives the identity)."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise ValueError(f"q: expected shape (..., 4), got {q.shape}")
    flat = q.reshape(-1, 4)
    zero = ~(np.abs(flat) > 0).any(axis=1)
    flat = np.where(zero[:, None], [1.0, 0.0, 0.0, 0.0], flat)
    R = Rotation.from_quat(flat, scalar_first=True).as_matrix() if len(flat) else \
        np.zeros((0, 3, 3))
    return R.reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) float64 unit quaternions w, x, y, z with w >= 0
    (q and -q are one rotation)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R: expected shape (..., 3, 3), got {R.shape}")
    flat = R.reshape(-1, 3, 3)
    q = Rotation.from_matrix(flat).as_quat(canonical=True, scalar_first=True) if len(flat) \
        else np.zeros((0, 4))
    return q.reshape(R.shape[:-2] + (4,))
