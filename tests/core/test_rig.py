"""Geometry from a calibrated rig on a scene the test draws itself: a textured roof of two planes
(a ridge along y), seen from above by a 3 x 3 grid of pinholes. Its depth and normals are known
exactly, so the fused stereo depth and the normal priors are checked against them."""

from __future__ import annotations

import numpy as np
import pytest

from core.config.rig import StereoConfig
from core.data.capture import Camera
from core.rig import rig_depth
from core.rig.geometry import RigGeometry
from core.rig.stereo import choose_sources

SLOPE = 0.5
"""The roof: z = -SLOPE |x| (the ridge at x = 0 is nearest the cameras above it)."""
SIZE = 64
HEIGHT = 3.0


def _texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A fixed random grey field on the roof, bilinear between cells of 0.15 (about 3 pixels at
    the cameras' distance: every window has texture, and point sampling does not alias)."""
    grid = np.random.default_rng(7).uniform(0.1, 0.9, (200, 200))
    gx, gy = (x + 15) / 0.15, (y + 15) / 0.15
    i, j = np.clip(np.floor(gx).astype(int), 0, 198), np.clip(np.floor(gy).astype(int), 0, 198)
    fx, fy = np.clip(gx - i, 0, 1), np.clip(gy - j, 0, 1)
    return ((1 - fx) * (1 - fy) * grid[i, j] + fx * (1 - fy) * grid[i + 1, j]
            + (1 - fx) * fy * grid[i, j + 1] + fx * fy * grid[i + 1, j + 1])


def _camera(cx: float, cy: float, name: str) -> Camera:
    """Looking down (-z) from (cx, cy, HEIGHT) with OpenCV axes: x right, y down = world -y."""
    R = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    center = np.array([cx, cy, HEIGHT])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ center
    K = np.array([[SIZE * 0.9, 0, SIZE / 2], [0, SIZE * 0.9, SIZE / 2], [0, 0, 1.0]])
    return Camera(name, SIZE, SIZE, K, w2c)


def _render(cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The roof seen by `cam`: image (H, W, 3), depth (H, W) and world normals (H, W, 3)."""
    v, u = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    rays = np.linalg.solve(cam.K, np.stack([u.ravel(), v.ravel(), np.ones(u.size)]))
    d = (cam.R.T @ rays).T  # world directions with camera z = 1
    o = cam.center
    best = np.full(len(d), np.inf)
    normal = np.zeros((len(d), 3))
    for side in (1.0, -1.0):  # the plane z = -SLOPE side x, kept where side x >= 0
        n = np.array([side * SLOPE, 0.0, 1.0])
        t = -(n @ o) / (d @ n)
        x = o[0] + t * d[:, 0]
        hit = (t > 0) & (side * x >= 0) & (t < best)
        best[hit] = t[hit]
        normal[hit] = n / np.linalg.norm(n)
    p = o + best[:, None] * d
    grey = _texture(p[:, 0], p[:, 1])
    image = np.repeat(grey[:, None], 3, axis=1).reshape(SIZE, SIZE, 3).astype(np.float32)
    return image, best.reshape(SIZE, SIZE), normal.reshape(SIZE, SIZE, 3)


@pytest.fixture(scope="module")
def roof():
    cams = [_camera(cx, cy, f"c{i}") for i, (cx, cy) in
            enumerate((x, y) for y in (-0.6, 0.0, 0.6) for x in (-0.6, 0.0, 0.6))]
    return cams, [_render(c) for c in cams]


def test_sources_are_chosen_by_angle(roof):
    cams, _ = roof
    cfg = StereoConfig(sources=4, min_angle=3, max_angle=45, target_angle=15)
    centre = choose_sources(cams, 4, HEIGHT, cfg)
    assert len(centre) == 4 and 4 not in centre
    # The nearest four (0.6 away: 11.3 degrees at the roof) come before the diagonals (16 deg
    # is nearer 15, but 0.85 away); with a 12 degree ceiling only the nearest four are left.
    assert sorted(choose_sources(cams, 4, HEIGHT, StereoConfig(max_angle=12))) == [1, 3, 5, 7]
    assert choose_sources(cams, 4, HEIGHT, StereoConfig(min_angle=30)) == []


def test_fused_depth_lies_on_the_known_surface(roof):
    cams, renders = roof
    images = [r[0] for r in renders]
    fused = rig_depth(cams, images, points=np.array([[0.0, 0.0, 0.0], [1.0, 1.0, -0.5]] * 8))
    # Most of each view survives the consistency check, and what survives is the roof: a tenth
    # of a pixel of disparity is 0.9% of depth here (11.5 pixels between neighbours).
    cover = [float((d > 0).mean()) for d in fused.depths]
    assert min(cover) > 0.4, cover
    for depth, (_, truth, _) in zip(fused.depths, renders):
        ok = depth > 0
        err = np.abs(depth[ok] - truth[ok]) / truth[ok]
        assert np.median(err) < 0.01 and np.percentile(err, 95) < 0.03, np.median(err)
    pts = fused.cloud.points
    height = -SLOPE * np.abs(pts[:, 0])
    rel = np.abs(pts[:, 2] - height) / (HEIGHT - height)  # the depth error along z
    assert len(pts) > 5000 and np.median(rel) < 0.01 and np.percentile(rel, 95) < 0.03
    # Its colours are the texture's grey.
    assert np.allclose(fused.cloud.colors[:, 0], fused.cloud.colors[:, 1])


def test_a_flat_view_has_no_depth(roof):
    cams, renders = roof
    flat = [np.full_like(r[0], 0.5) for r in renders]
    fused = rig_depth(cams, flat, points=np.array([[0.0, 0.0, 0.0], [1.0, 1.0, -0.5]] * 8))
    assert len(fused.cloud) == 0 and all(not d.any() for d in fused.depths)


def test_normal_priors_match_the_true_normals(roof):
    cams, renders = roof
    rig = RigGeometry(cams, [r[0] for r in renders], [None] * len(cams))
    priors = rig.priors()
    for (normal, conf, measured), (_, _, truth) in zip(priors, renders):
        assert normal.shape == (SIZE, SIZE, 3) and conf.shape == (SIZE, SIZE, 1)
        # no mattes, so no hull: every prior is stereo's
        assert np.array_equal(measured > 0, conf > 0)
        has = conf[..., 0] > 0
        assert has.mean() > 0.4
        cos = (normal * truth).sum(-1)
        # Confident priors are the roof's planes; the ridge (where the window holds both) and
        # what fusion dropped have little or no confidence.
        sure = conf[..., 0] > 0.5
        assert np.median(cos[sure]) > 0.99 and np.percentile(cos[sure], 5) > 0.9
        assert np.percentile(cos[has], 10) > 0.9
    assert set(rig.seconds) == {"triangulation", "stereo", "priors"}


def test_the_nearest_surface_is_the_ridge_and_a_close_one_is_told(roof):
    from core.pipeline.frame import near_note

    cams, renders = roof
    rig = RigGeometry(cams, [r[0] for r in renders], [None] * len(cams))
    assert rig.nearest() is None  # nothing fused yet, and asking does not fuse
    rig.fused()
    truth = min(float(np.percentile(r[1], 1)) for r in renders)  # the ridge, 3.0 below
    assert rig.nearest() == pytest.approx(truth, rel=0.03)
    assert near_note(rig.nearest(), near=1.0) is None  # 3.0 is beyond twice the plane
    note = near_note(rig.nearest(), near=1.6)
    assert note is not None and f"train.near below {rig.nearest() / 2:.3g}" in note
    assert near_note(None, near=1.6) is None
