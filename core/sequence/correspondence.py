"""How well tracked Gaussians keep their correspondence, against ground truth that has it.

A synthetic capture's ground-truth meshes (gt/meshes/<frame>.ply) are one mesh posed per frame:
vertex i is the same point of the body in every frame. Each opaque Gaussian of a group's key frame
(opacity_c >= 0.5) is tied to its nearest vertex there, its offset kept in that vertex's local
frame (normal, and the edge to a fixed neighbour); in every later frame of the group the Gaussian
with the same track id should sit at the vertex's new position plus the offset turned with the
vertex's frame. The track error is the distance from where it should be, averaged with the
Gaussians' key-frame opacities as weights (a faint Gaussian misplaced matters less), as a
percentage of the
ground truth's bounding-box diagonal (like the Chamfer distance of meshes). Held-out PSNR cannot
see a track that jumped to the wrong limb of the same colour, or two feet that swapped Gaussians;
this can. None when the capture has no such meshes or their vertex counts differ between frames.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from core.plyio import read_mesh_ply
from core.sequence.tracks import load_frame
from core.synth.figure import vertex_normals

__all__ = ["track_errors"]


def _frames_of(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3, 3) orthonormal frames [tangent, bitangent, normal] as columns per vertex."""
    n = vertex_normals(vertices, faces)
    neighbour = np.zeros(len(vertices), dtype=np.int64)
    neighbour[faces[:, 0]] = faces[:, 1]  # a fixed neighbour per vertex (the same every frame)
    neighbour[faces[:, 1]] = faces[:, 2]
    neighbour[faces[:, 2]] = faces[:, 0]
    e = vertices[neighbour] - vertices
    t = e - (e * n).sum(1, keepdims=True) * n
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    return np.stack([t, np.cross(n, t), n], axis=2)


def _mesh(gt: Path, frame: str) -> tuple[np.ndarray, np.ndarray] | None:
    path = gt / "meshes" / f"{frame}.ply"
    return read_mesh_ply(path) if path.is_file() else None


def track_errors(run_dir, capture_dir) -> dict | None:
    """{"track_error": mean over the deformed frames (% of the diagonal), "track_error_mm"
    (scene units x 1000), "track_error_per_frame": per frame in sequence.json order (None for
    key frames), "tracked_gaussians": how many key-frame Gaussians were followed}; None without
    usable ground truth (module docstring)."""
    run, gt = Path(run_dir), Path(capture_dir) / "gt"
    seq_path = run / "sequence.json"
    if not seq_path.is_file():
        return None
    rows = [r for r in json.loads(seq_path.read_text())["frames"] if r["done"]]
    per_frame: list[float | None] = []
    errors, diagonal, ties, followed = [], None, {}, 0
    for r in rows:
        mesh = _mesh(gt, r["frame"])
        ply = run / "frames" / r["frame"] / "gaussians.ply"
        if mesh is None or not ply.is_file():
            return None
        vertices, faces = mesh
        model, ids = load_frame(ply)
        means = model.means.detach().double().cpu().numpy()
        ids = ids.cpu().numpy()
        basis = _frames_of(vertices, faces)
        if diagonal is None:
            diagonal = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        if r["role"] == "key":
            opacity = model.opacity_c.detach().double().cpu().numpy()
            opaque = opacity >= 0.05
            _, nearest = cKDTree(vertices).query(means[opaque])
            local = np.einsum("vji,vj->vi", basis[nearest], means[opaque] - vertices[nearest])
            ties = {"ids": ids[opaque], "vertex": nearest, "local": local,
                    "weight": opacity[opaque], "count": len(vertices)}
            followed += int(opaque.sum())
            per_frame.append(None)
            continue
        if len(vertices) != ties.get("count"):
            return None  # not one mesh posed per frame: no correspondence to compare with
        where = {int(i): k for k, i in enumerate(ids)}
        rows_here = [(k, where[int(i)]) for k, i in enumerate(ties["ids"]) if int(i) in where]
        if not rows_here:
            per_frame.append(None)
            continue
        tied, found = (np.array(c) for c in zip(*rows_here))
        v = ties["vertex"][tied]
        should = vertices[v] + np.einsum("vij,vj->vi", basis[v], ties["local"][tied])
        err = float(np.average(np.linalg.norm(means[found] - should, axis=1),
                               weights=ties["weight"][tied]))
        errors.append(err)
        per_frame.append(round(100.0 * err / diagonal, 4))
    if not errors:
        return None
    mean = float(np.mean(errors))
    return {"track_error": round(100.0 * mean / diagonal, 4),
            "track_error_mm": round(1000.0 * mean, 2),
            "track_error_per_frame": per_frame, "tracked_gaussians": followed}
