"""From a fused TSDF to a clean triangle mesh: marching cubes (scikit-image, Lewiner et al. 2003),
the largest components, no degenerate faces, outward-facing triangles; export with trimesh.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from skimage.measure import marching_cubes

from core.config import MESH_FORMATS
from core.files import atomic_path

__all__ = ["FORMATS", "clean_mesh", "export_mesh", "extract_surface", "transform_mesh"]

FORMATS = MESH_FORMATS
"""The file formats a mesh is written in."""


def extract_surface(values: np.ndarray, lo: np.ndarray, voxel: float):
    """The zero level set of `values` (X, Y, Z) (negative inside) as a trimesh.Trimesh in world
    coordinates, closed: the grid is padded with one layer of +1 (outside) first."""
    padded = np.pad(values.astype(np.float32), 1, mode="constant", constant_values=1.0)
    if padded.min() >= 0 or padded.max() <= 0:
        raise ValueError("tsdf: no surface in the volume (every voxel is on one side); check "
                         "the depth maps, the coverage threshold and the box")
    # scikit-image's default 'descent' winding faces from negative to positive values: outwards.
    verts, faces, _, _ = marching_cubes(padded, level=0.0, spacing=(voxel,) * 3,
                                        allow_degenerate=False)
    # Padding shifts indices by one; voxel i has its centre at lo + (i + 0.5) voxel.
    verts = verts + (np.asarray(lo) + (0.5 - 1.0) * voxel)
    return trimesh.Trimesh(verts, faces, process=True)


def clean_mesh(mesh, min_component: float = 0.05):
    """Drop degenerate and duplicate faces and unreferenced vertices, then every connected
    component with fewer than `min_component` x the faces of the largest (1.0 keeps only the
    largest)."""
    if not 0 < min_component <= 1:
        raise ValueError(f"min_component: expected a fraction in (0, 1], got {min_component}")
    mesh = mesh.copy()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise ValueError("mesh: nothing left after removing degenerate faces")
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        largest = max(len(p.faces) for p in parts)
        keep = [p for p in parts if len(p.faces) >= min_component * largest]
        mesh = trimesh.util.concatenate(keep)
    return mesh


def transform_mesh(mesh, matrix: np.ndarray | None):
    """A copy of `mesh` with the 4x4 `matrix` applied (None: unchanged); a reflection also flips
    the faces so they keep facing outwards."""
    if matrix is None:
        return mesh
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ValueError(f"transform: expected a finite 4x4 matrix, got shape {m.shape}")
    out = mesh.copy()
    out.apply_transform(m)  # trimesh flips winding itself when the determinant is negative
    return out


def export_mesh(mesh, stem: Path, formats=("ply",)) -> list[Path]:
    """stem.<fmt> for each format (ply, obj, glb); vertex colours are kept in all three."""
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise ValueError(f"formats: expected some of {FORMATS}, got {list(formats)}")
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    out = []
    for fmt in formats:
        path = stem.with_suffix(f".{fmt}")
        with atomic_path(path) as tmp:
            tmp.write_bytes(_export_bytes(mesh, fmt))
        out.append(path)
    return out


def _export_bytes(mesh, fmt: str) -> bytes:
    data = mesh.export(file_type=fmt, **({"include_color": True} if fmt == "obj" else {}))
    return data.encode() if isinstance(data, str) else data
