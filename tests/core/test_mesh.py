"""core.mesh: TSDF fusion of an analytic sphere, surface cleanup and export, the Chamfer and
normal-consistency metrics against closed forms, and a tiny run meshed end to end (CLI too)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from core.config import MeshConfig
from core.mesh import (
    TSDFVolume,
    clean_mesh,
    export_mesh,
    extract_surface,
    mesh_distance,
    mesh_run,
    transform_mesh,
)
from core.synth.generate import look_at
from core.synth.shading import fibonacci_sphere

pytestmark = pytest.mark.usefixtures("one_thread")

CENTER, RADIUS = np.array([0.1, -0.2, 0.3]), 0.5


def _sphere_depth(w2c: np.ndarray, K: np.ndarray, size: int) -> np.ndarray:
    """Camera z of the first hit of each pixel-centre ray on the sphere (0: miss)."""
    v, u = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5, indexing="ij")
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z = 1
    c = w2c[:3, :3] @ CENTER + w2c[:3, 3]
    a, b = (rays * rays).sum(-1), -2 * (rays @ c)
    disc = b * b - 4 * a * (c @ c - RADIUS**2)
    return np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0.0)


@pytest.fixture(scope="module")
def sphere_mesh():
    size = 40
    K = np.array([[40.0, 0, size / 2], [0, 40.0, size / 2], [0, 0, 1]])
    depths, Ks, views = [], [], []
    # Evenly spread views: every patch of the sphere is seen (random ones can leave a patch
    # unobserved, which fusion fills as inside, as it must).
    for d in fibonacci_sphere(16):
        w2c = look_at(CENTER + 2.5 * d, CENTER, (0, 0, 1.0) if abs(d[2]) < 0.9 else (1.0, 0, 0))
        depths.append(torch.tensor(_sphere_depth(w2c, K, size), dtype=torch.float32))
        Ks.append(torch.tensor(K, dtype=torch.float32))
        views.append(torch.tensor(w2c, dtype=torch.float32))
    voxel = 2 * RADIUS / 40
    vol = TSDFVolume.create(CENTER - 0.65, CENTER + 0.65, voxel, 5.0, chunk=20_000)
    vol.integrate(depths, Ks, views)
    return clean_mesh(extract_surface(vol.values(), vol.lo, voxel)), voxel


def test_tsdf_of_a_sphere(sphere_mesh):
    mesh, voxel = sphere_mesh
    r = np.linalg.norm(mesh.vertices - CENTER, axis=1)
    assert np.abs(r - RADIUS).max() < 0.5 * voxel  # marching cubes on a smooth field
    assert mesh.is_watertight and len(mesh.split()) == 1
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * RADIUS**3, rel=0.03)
    outward = ((mesh.triangles_center - CENTER) * mesh.face_normals).sum(1) > 0
    assert outward.all()


def _pedestal_depth(w2c: np.ndarray, K: np.ndarray, size: int, radius: float,
                    z0: float, z1: float) -> np.ndarray:
    """Camera z of the first hit of each pixel-centre ray on a closed upright cylinder about
    the z axis from z0 to z1 (0: miss)."""
    v, u = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5, indexing="ij")
    d = (np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T) @ w2c[:3, :3]  # t = z
    o = -w2c[:3, :3].T @ w2c[:3, 3]
    best = np.full(d.shape[:2], np.inf)
    a = d[..., 0] ** 2 + d[..., 1] ** 2
    b = 2 * (o[0] * d[..., 0] + o[1] * d[..., 1])
    disc = b * b - 4 * a * (o[0] ** 2 + o[1] ** 2 - radius**2)
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * np.maximum(a, 1e-12))
    z = o[2] + t * d[..., 2]
    best = np.where((disc > 0) & (t > 0) & (z >= z0) & (z <= z1), t, best)
    for plane in (z0, z1):
        t = (plane - o[2]) / np.where(np.abs(d[..., 2]) > 1e-12, d[..., 2], 1e-12)
        x, y = o[0] + t * d[..., 0], o[1] + t * d[..., 1]
        best = np.where((t > 0) & (x * x + y * y <= radius**2) & (t < best), t, best)
    return np.where(np.isfinite(best), best, 0.0)


def test_an_unseen_bottom_closes_at_the_lowest_observed_surface():
    """A pedestal filmed by cameras all above the horizon (elevations 25-70 degrees): its bottom
    is never seen. Unseen space inside their views used to be filled under it down to where the
    views end (the silhouettes' cone, a slab under the pedestal); with the up axis the mesh ends
    at the lowest observed surface, the pedestal's foot, and matches the truth."""
    import trimesh

    size, radius, z0, z1 = 48, 0.3, -0.4, 0.4
    K = np.array([[48.0, 0, size / 2], [0, 48.0, size / 2], [0, 0, 1]])
    depths, Ks, views = [], [], []
    for i in range(12):
        az, el = 2 * math.pi * i / 12, math.radians(25 + 45 * (i % 3) / 2)
        d = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
        w2c = look_at(3.0 * d, np.zeros(3), (0, 0, 1.0))
        depths.append(torch.tensor(_pedestal_depth(w2c, K, size, radius, z0, z1),
                                   dtype=torch.float32))
        Ks.append(torch.tensor(K, dtype=torch.float32))
        views.append(torch.tensor(w2c, dtype=torch.float32))
    voxel = 0.02
    vol = TSDFVolume.create(np.full(3, -0.8), np.full(3, 0.8), voxel, 5.0, chunk=50_000)
    vol.integrate(depths, Ks, views)
    cone = clean_mesh(extract_surface(vol.values(), vol.lo, voxel))
    closed = clean_mesh(extract_surface(vol.values(up=(0, 0, 1.0)), vol.lo, voxel))
    truth = trimesh.creation.cylinder(radius=radius, height=z1 - z0)
    assert cone.vertices[:, 2].min() < z0 - 10 * voxel  # the slab under the pedestal
    # Within the truncation: fused voxels just under the rim, behind the side, are inside.
    assert closed.vertices[:, 2].min() > z0 - 4 * voxel and closed.is_watertight
    chamfer = [mesh_distance(m, truth)["chamfer"] for m in (closed, cone)]
    assert chamfer[0] < 0.5 * chamfer[1] and chamfer[0] < voxel


def test_chamfer_and_normal_consistency_closed_forms(sphere_mesh):
    import trimesh

    a = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    b = trimesh.creation.icosphere(subdivisions=5, radius=1.1)
    # Concentric spheres: every point's nearest neighbour is radial, at |r1 - r2| = 0.1.
    m = mesh_distance(a, b, samples=20_000)
    assert m["chamfer"] == pytest.approx(0.1, rel=0.05)
    assert m["normal_consistency"] > 0.99
    assert m["chamfer_relative"] == pytest.approx(m["chamfer"] / (2.2 * math.sqrt(3)), rel=0.02)
    # Against itself only sampling noise is left: two independent uniform samplings of area A
    # with n points each are a mean nearest-neighbour distance 1 / (2 sqrt(n / A)) apart
    # (Clark & Evans 1954, Poisson points in the plane).
    noise = 0.5 * math.sqrt(a.area / 20_000)
    assert mesh_distance(a, a, samples=20_000)["chamfer"] == pytest.approx(noise, rel=0.1)
    # A sphere against a cube of the same size: normals disagree away from the face centres.
    cube = trimesh.creation.box(extents=(2, 2, 2))
    assert mesh_distance(a, cube, samples=20_000)["normal_consistency"] < 0.95
    mesh, _ = sphere_mesh
    ref = trimesh.creation.icosphere(subdivisions=5, radius=RADIUS).apply_translation(CENTER)
    assert mesh_distance(mesh, ref, samples=20_000)["chamfer_relative"] < 0.005


def test_cleanup_drops_small_parts_and_degenerate_faces():
    import trimesh

    big = trimesh.creation.icosphere(subdivisions=3)
    speck = trimesh.creation.icosphere(subdivisions=0, radius=0.01).apply_translation([3, 0, 0])
    both = trimesh.util.concatenate([big, speck])
    faces = np.vstack([both.faces, [[0, 0, 1]]])  # a degenerate triangle
    dirty = trimesh.Trimesh(both.vertices, faces, process=False)
    clean = clean_mesh(dirty, 0.05)
    assert len(clean.faces) == len(big.faces) and clean.is_watertight
    assert len(clean_mesh(dirty, 0.001).split()) == 2
    with pytest.raises(ValueError, match="min_component"):
        clean_mesh(dirty, 0.0)


def test_no_surface_is_an_error():
    with pytest.raises(ValueError, match="no surface"):
        extract_surface(np.ones((4, 4, 4), np.float32), np.zeros(3), 0.1)


def test_export_keeps_colours_and_orientation(tmp_path: Path):
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2)
    mesh.visual.vertex_colors = np.tile([[200, 30, 10, 255]], (len(mesh.vertices), 1))
    files = export_mesh(mesh, tmp_path / "m", ("ply", "obj", "glb"))
    assert [p.name for p in files] == ["m.ply", "m.obj", "m.glb"]
    for path in files:
        back = trimesh.load(path, force="mesh")
        assert len(back.faces) == len(mesh.faces), path.name
        visual = back.visual.to_color() if hasattr(back.visual, "to_color") else back.visual
        colors = np.asarray(visual.vertex_colors)[:, :3]
        np.testing.assert_allclose(colors.mean(0), [200, 30, 10], atol=2), path.name
    flip = np.diag([-1.0, 1, 1, 1])
    flip[:3, 3] = [1, 2, 3]
    moved = transform_mesh(mesh, flip)
    assert moved.volume > 0  # a reflection keeps the faces outward
    np.testing.assert_allclose(moved.centroid, [1, 2, 3], atol=1e-6)
    with pytest.raises(ValueError, match="formats"):
        export_mesh(mesh, tmp_path / "m", ("stl",))


def test_mesh_config_checks():
    for bad, message in [({"resolution": 4}, "resolution"), ({"depth": "rgb"}, "depth"),
                         ({"formats": ("fbx",)}, "formats"), ({"alpha_threshold": 1.0}, "alpha")]:
        with pytest.raises(ValueError, match=message):
            MeshConfig(**bad)
