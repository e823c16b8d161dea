"""`dgs synth`: valid output, consistent ground truth, real motion, determinism, degraded priors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from core.cli import main
from core.data import load_capture, validate_capture
from core.plyio import read_mesh_ply
from core.synth import SynthConfig, rasterize, synthesize


def _point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Exact distance from points (N, 3) to triangles (N, 3, 3), one triangle per point."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    proj = p - ((p - a) * n).sum(1, keepdims=True) * n
    inside = np.ones(len(p), bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= (np.cross(v - u, proj - u) * n).sum(1) >= 0
    best = np.where(inside, np.abs(((p - a) * n).sum(1)), np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        t = np.clip(((p - u) * (v - u)).sum(1) / ((v - u) ** 2).sum(1), 0, 1)
        best = np.minimum(best, np.linalg.norm(p - (u + t[:, None] * (v - u)), axis=1))
    return best


def _mesh_distance(points: np.ndarray, V: np.ndarray, F: np.ndarray, k: int = 24) -> np.ndarray:
    from scipy.spatial import cKDTree

    centroids = V[F].mean(axis=1)
    _, idx = cKDTree(centroids).query(points, k=k)
    d = np.stack([_point_triangle_distance(points, V[F[idx[:, j]]]) for j in range(k)], axis=1)
    return d.min(axis=1)


def test_output_validates_and_has_ground_truth(synth_capture: Path) -> None:
    assert validate_capture(synth_capture) == []
    cap = load_capture(synth_capture)
    assert cap.up == (0.0, 0.0, 1.0)
    gt = synth_capture / "gt"
    for frame in cap.frames:
        assert (gt / "meshes" / f"{frame}.ply").is_file()
        for cam in cap.cameras:
            for sub, ext in (
                ("depth", "npy"),
                ("normals", "npy"),
                ("relight", "png"),
                ("albedo", "png"),
            ):
                assert (gt / sub / frame / f"{cam.id}.{ext}").is_file()
            assert cap.normal_path(frame, cam.id) is not None
    lights = json.loads((gt / "lights.json").read_text())
    assert set(lights["lights"]) == {"capture", "relight"}
    assert np.array(lights["lights"]["relight"]["sh9_radiance"]).shape == (9, 3)


def test_depth_back_projects_onto_mesh(synth_capture: Path) -> None:
    cap = load_capture(synth_capture)
    for frame in cap.frames:
        V, F = read_mesh_ply(synth_capture / "gt" / "meshes" / f"{frame}.ply")
        diag = np.linalg.norm(V.max(0) - V.min(0))
        dists = []
        for cam in cap.cameras:
            depth = np.load(synth_capture / "gt" / "depth" / frame / f"{cam.id}.npy")
            cover = np.asarray(__import__("PIL.Image").Image.open(cap.mask_path(frame, cam.id)))
            # Depth is point-sampled at pixel centres, the mask is coverage: a centre on the
            # figure means some coverage, full coverage means the centre is on it.
            assert np.all(cover[depth > 0] > 0) and np.all(depth[cover == 255] > 0)
            mask = depth > 0
            v, u = np.nonzero(mask)
            rays = (
                np.stack([u + 0.5, v + 0.5, np.ones_like(u, dtype=float)], 1)
                @ np.linalg.inv(cam.K).T
            )
            points = (rays * depth[v, u, None] - cam.t) @ cam.R
            dists.append(_mesh_distance(points, V, F))
        d = np.concatenate(dists)
        assert d.mean() < 0.005 * diag  # the acceptance criterion
        assert d.mean() < 1e-5 * diag  # float32 storage is the only error left


def test_normals_face_the_camera_and_are_unit(synth_capture: Path) -> None:
    cap = load_capture(synth_capture)
    cam = cap.cameras[0]
    n = np.load(synth_capture / "gt/normals/000000" / f"{cam.id}.npy")
    depth = np.load(synth_capture / "gt/depth/000000" / f"{cam.id}.npy")
    fg = depth > 0
    np.testing.assert_allclose(np.linalg.norm(n[fg], axis=1), 1.0, atol=1e-5)
    v, u = np.nonzero(fg)
    rays = (
        np.stack([u + 0.5, v + 0.5, np.ones_like(u, dtype=float)], 1)
        @ np.linalg.inv(cam.K).T
        @ cam.R
    )
    facing = (n[fg] * rays).sum(1) < 0
    assert facing.mean() > 0.95  # smooth normals tilt slightly away only at silhouettes


def test_motion_is_non_rigid(synth_capture: Path) -> None:
    V0, _ = read_mesh_ply(synth_capture / "gt/meshes/000000.ply")
    V1, _ = read_mesh_ply(synth_capture / "gt/meshes/000001.ply")
    # Best rigid fit (Kabsch) between frames leaves a large residual when limbs move on their own.
    a, b = V0 - V0.mean(0), V1 - V1.mean(0)
    U, _, Wt = np.linalg.svd(a.T @ b)
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Wt))])
    residual = np.linalg.norm(a @ (U @ D @ Wt) - b, axis=1)
    assert residual.max() > 0.1 and residual.mean() > 0.02


def test_relight_differs_and_priors_are_degraded(synth_capture: Path) -> None:
    from PIL import Image

    img = np.asarray(Image.open(synth_capture / "images/000000/cam03.png"), dtype=float)
    rel = np.asarray(Image.open(synth_capture / "gt/relight/000000/cam03.png"), dtype=float)
    cover = np.asarray(Image.open(synth_capture / "masks/000000/cam03.png"))
    mask = cover > 0
    assert np.abs(img - rel)[mask].mean() > 10
    assert img[~mask].max() == 0 and img[mask].mean() > 30
    # Straight colour: silhouette pixels are as bright as the figure's inside, not darkened
    # by the black background their coverage leaves out.
    edge, inside = (cover > 0) & (cover < 255), cover == 255
    assert edge.sum() > 20 and img[edge].mean() > 0.8 * img[inside].mean()
    prior = (
        np.asarray(Image.open(synth_capture / "normals/000000/cam03.png"), dtype=float) / 255 * 2
        - 1
    )
    gt = np.load(synth_capture / "gt/normals/000000/cam03.npy")
    prior /= np.linalg.norm(prior, axis=2, keepdims=True)
    angle = np.degrees(np.arccos(np.clip((prior * gt).sum(2), -1, 1)))[cover == 255]
    assert 2.0 < np.median(angle) < 25.0


def test_deterministic_for_a_seed(synth_capture: Path, tmp_path: Path, digest, tiny_config) -> None:
    synthesize(tmp_path / "again", tiny_config)
    assert digest(tmp_path / "again") == digest(synth_capture)
    other = SynthConfig(**{**tiny_config.__dict__, "seed": tiny_config.seed + 1, "frames": 1})
    synthesize(tmp_path / "other", other)
    a = (tmp_path / "other/images/000000/cam00.png").read_bytes()
    assert a != (synth_capture / "images/000000/cam00.png").read_bytes()


def test_rasterizer_matches_brute_force() -> None:
    rng = np.random.default_rng(0)
    W, H = 23, 17
    xy = rng.uniform(-3, 26, size=(30, 2))
    z = rng.uniform(1, 5, size=30)
    faces = rng.integers(0, 30, size=(12, 3))
    frags = rasterize(xy, z, faces, W, H, perspective=True)
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    q = np.stack([xx.ravel(), yy.ravel()], 1)
    best = np.full(W * H, np.inf)

    def cross(u, v):
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    for f in faces:
        a, b, c = xy[f]
        area = cross(b - a, c - a)
        if abs(area) < 1e-12:
            continue
        l0 = cross(b - q, c - q) / area
        l1 = cross(c - q, a - q) / area
        l2 = 1 - l0 - l1
        inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
        depth = 1 / (l0 / z[f[0]] + l1 / z[f[1]] + l2 / z[f[2]])
        best = np.where(inside, np.minimum(best, depth), best)
    best = best.reshape(H, W)
    np.testing.assert_array_equal(frags.mask, np.isfinite(best))
    np.testing.assert_allclose(frags.depth[frags.mask], best[frags.mask], rtol=1e-12)


def test_cli_synth(tmp_path: Path, capsys) -> None:
    out = tmp_path / "s"
    assert (
        main(
            [
                "synth",
                str(out),
                "--frames",
                "1",
                "--views",
                "3",
                "--size",
                "24",
                "20",
                "--seed",
                "5",
            ]
        )
        == 0
    )
    cap = load_capture(out)
    assert (cap.cameras[0].width, cap.cameras[0].height) == (24, 20) and len(cap.cameras) == 3
    assert not (out / "normals").exists()
    assert main(["synth", str(out)]) == 2  # refuses to overwrite
    assert "not an empty folder" in capsys.readouterr().err


def test_coverage_is_the_area_average(tmp_path: Path) -> None:
    """Supersampled masks and images agree with a 3x larger capture averaged over 3x3 blocks
    (same cameras, intrinsics scaled), i.e. masks are coverage and image * mask the premultiplied
    area average."""
    from PIL import Image

    base = SynthConfig(frames=1, views=2, width=16, height=16, seed=4, ao_directions=4)
    synthesize(tmp_path / "ss", base)
    cap = load_capture(tmp_path / "ss")
    big = cap.cameras[1].scaled(48, 48)
    from core.synth.figure import Figure
    from core.synth.generate import _render_view, _subject
    from core.synth.shading import vertex_visibility

    rng = np.random.default_rng(base.seed)
    figure = Figure(seed=int(rng.integers(2**31)))
    palette = rng.uniform(0.25, 0.85, size=(figure.n_parts, 3))
    mesh = figure.pose(0.0)
    vis = vertex_visibility(mesh.vertices, mesh.normals, mesh.faces, base.ao_directions)
    point = _render_view(mesh, vis, big, _subject(base, figure, palette)[1], supersample=1)
    cover = point["mask"].reshape(16, 3, 16, 3).mean(axis=(1, 3))
    pre = (point["capture"] * point["mask"][..., None]).reshape(16, 3, 16, 3, 3).mean(axis=(1, 3))
    mask = np.asarray(Image.open(tmp_path / "ss/masks/000000/cam01.png")) / 255.0
    img = np.asarray(Image.open(tmp_path / "ss/images/000000/cam01.png")) / 255.0
    assert ((cover > 0) & (cover < 1)).sum() > 10
    np.testing.assert_allclose(mask, cover, atol=0.5 / 255 + 1e-9)
    np.testing.assert_allclose(img * mask[..., None], pre, atol=1.5 / 255)


@pytest.mark.parametrize(("bad", "named"), [({"views": 0}, "views"), ({"width": 4}, "size"),
                                           ({"supersample": 2}, "supersample")])
def test_config_is_checked(bad: dict, named: str, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=named):
        synthesize(tmp_path / "x", SynthConfig(**bad))
