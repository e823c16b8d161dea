"""Mesh accuracy against a reference mesh: symmetric Chamfer distance (docs/design.md section 5: the
mean of both directions' mean nearest-neighbour distances) and normal consistency (Mescheder et
al. 2019, Occupancy Networks: the mean |cos| between a sample's face normal and the normal of its
nearest neighbour on the other mesh, averaged over both directions), on points sampled uniformly
by area.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

__all__ = ["mesh_distance"]


def _sample(mesh, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    pts, face = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(pts), np.asarray(mesh.face_normals)[face]


def mesh_distance(pred, reference, *, samples: int = 100_000, seed: int = 0) -> dict:
    """{"chamfer", "chamfer_pred_to_ref", "chamfer_ref_to_pred", "chamfer_relative",
    "normal_consistency", "reference_diagonal"} of trimesh meshes `pred` and `reference`
    (same coordinates); chamfer_relative divides by the reference's bounding-box diagonal."""
    for name, m in (("pred", pred), ("reference", reference)):
        if len(m.faces) == 0 or not float(m.area) > 0:
            raise ValueError(f"{name}: expected a mesh with faces of non-zero area")
    if samples < 1:
        raise ValueError(f"samples: expected >= 1, got {samples}")
    pa, na = _sample(pred, samples, seed)
    pb, nb = _sample(reference, samples, seed + 1)
    d_ab, i_ab = cKDTree(pb).query(pa, workers=-1)
    d_ba, i_ba = cKDTree(pa).query(pb, workers=-1)
    nc_ab = np.abs((na * nb[i_ab]).sum(1)).mean()
    nc_ba = np.abs((nb * na[i_ba]).sum(1)).mean()
    diag = float(np.linalg.norm(np.ptp(np.asarray(reference.vertices), axis=0)))
    chamfer = 0.5 * (float(d_ab.mean()) + float(d_ba.mean()))
    return {"chamfer": chamfer, "chamfer_pred_to_ref": float(d_ab.mean()),
            "chamfer_ref_to_pred": float(d_ba.mean()), "chamfer_relative": chamfer / diag,
            "normal_consistency": float(0.5 * (nc_ab + nc_ba)), "reference_diagonal": diag}
