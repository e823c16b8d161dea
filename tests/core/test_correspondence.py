"""Track error against ground-truth correspondences (core.sequence.correspondence): zero for
Gaussians that ride their vertices exactly, the displacement when one is moved, and None when
the ground truth has no correspondence."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from core.model import GaussianModel
from core.plyio import write_mesh_ply
from core.sequence.correspondence import track_errors
from core.sequence.tracks import save_frame
from core.synth.figure import vertex_normals


def _box() -> tuple[np.ndarray, np.ndarray]:
    """A closed octahedron-like mesh of 6 vertices, 8 faces (diagonal 2 sqrt(3) of its box)."""
    v = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                  [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return v, f


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _write_run(root: Path, poses: list[np.ndarray], points: list[np.ndarray],
               ids: list[np.ndarray], opacity: np.ndarray) -> tuple[Path, Path]:
    run, capture = root / "run", root / "capture"
    _, faces = _box()
    rows = []
    for k, (pose, pts, track) in enumerate(zip(poses, points, ids)):
        frame = f"{k:06d}"
        write_mesh_ply(capture / "gt" / "meshes" / f"{frame}.ply", pose, faces,
                  vertex_normals(pose, faces))
        model = GaussianModel.from_points(torch.tensor(pts, dtype=torch.float32))
        with torch.no_grad():
            model.params["opacity_c"].copy_(torch.logit(torch.tensor(opacity[track],
                                                                     dtype=torch.float32)))
        (run / "frames" / frame).mkdir(parents=True)
        save_frame(run / "frames" / frame / "gaussians.ply", model,
                   None if k == 0 else torch.tensor(track))
        rows.append({"frame": frame, "gop": 0, "role": "key" if k == 0 else "deformed",
                     "done": True})
    (run / "sequence.json").write_text(json.dumps({"frames": rows}))
    return run, capture


def test_gaussians_riding_their_vertices_have_no_error_and_a_moved_one_counts(tmp_path: Path):
    rest, _ = _box()
    # Gaussians at each vertex, pushed out along it by 0.1 (an offset in the vertex's frame).
    key = rest * 1.1
    moved = rest @ _rot_z(0.7).T + np.array([0.3, -0.2, 0.5])  # a rigid motion of the body
    follows = key @ _rot_z(0.7).T + np.array([0.3, -0.2, 0.5])  # ... and the Gaussians with it
    order = np.array([3, 0, 5, 1, 4, 2])  # the next frame lists them in another order
    opacity = np.array([0.9, 0.5, 0.5, 0.5, 0.5, 0.01])  # the last draws nothing: not tied
    run, capture = _write_run(tmp_path, [rest, moved], [key, follows[order]],
                              [np.arange(6), order], opacity)
    got = track_errors(run, capture)
    assert got["tracked_gaussians"] == 5
    assert got["track_error_per_frame"][0] is None
    assert got["track_error"] == pytest.approx(0.0, abs=1e-4)

    shifted = follows.copy()
    shifted[0] += np.array([0.0, 0.0, 0.3])  # Gaussian 0 (opacity 0.9) leaves its vertex by 0.3
    run2, _ = _write_run(tmp_path / "b", [rest, moved], [key, shifted[order]],
                         [np.arange(6), order], opacity)
    got = track_errors(run2, tmp_path / "b" / "capture")
    diagonal = 2 * math.sqrt(3)
    want = 0.9 * 0.3 / (0.9 + 4 * 0.5)  # opacity-weighted mean over the 5 tied Gaussians
    assert got["track_error"] == pytest.approx(100 * want / diagonal, rel=1e-4)
    assert got["track_error_mm"] == pytest.approx(1000 * want, rel=1e-3)


def test_no_correspondence_no_score(tmp_path: Path):
    rest, faces = _box()
    run, capture = _write_run(tmp_path, [rest, rest], [rest, rest], [np.arange(6)] * 2,
                              np.full(6, 0.5))
    assert track_errors(run, capture) is not None
    # A frame whose mesh has other vertices (remeshed, not posed) has nothing to compare with.
    write_mesh_ply(capture / "gt" / "meshes" / "000001.ply", np.vstack([rest, rest[:1] * 2]), faces)
    assert track_errors(run, capture) is None
    assert track_errors(run, tmp_path / "elsewhere") is None  # no ground truth at all
    (run / "sequence.json").unlink()
    assert track_errors(run, capture) is None  # not a sequence run
