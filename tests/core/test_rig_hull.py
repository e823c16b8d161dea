"""The visual hull's normal priors (`core.rig.hull`) on a sphere the test draws itself: a ring of
pinholes whose mattes are the sphere's exact silhouettes. The hull of a sphere seen from all
round is close to the sphere, so its normals are checked against the sphere's."""

from __future__ import annotations

import numpy as np

from core.data.capture import Camera
from core.rig.hull import HULL_CONFIDENCE, hull_normals

SIZE = 64
RADIUS = 1.0


def _look_at(center: np.ndarray, name: str) -> Camera:
    """A pinhole at `center` looking at the origin (OpenCV axes: x right, y down)."""
    forward = -center / np.linalg.norm(center)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ center
    K = np.array([[SIZE * 1.2, 0, SIZE / 2], [0, SIZE * 1.2, SIZE / 2], [0, 0, 1.0]])
    return Camera(name, SIZE, SIZE, K, w2c)


def _sphere(cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sphere seen by `cam`: matte (H, W, 1), world normals (H, W, 3) (zero off it) and
    each pixel's unit ray (H, W, 3)."""
    v, u = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    rays = np.linalg.solve(cam.K, np.stack([u.ravel(), v.ravel(), np.ones(u.size)]))
    d = (cam.R.T @ rays).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = cam.center
    b = d @ o
    disc = b * b - (o @ o - RADIUS ** 2)
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0.0))
    normal = np.where(hit[:, None], o + t[:, None] * d, 0.0) / RADIUS
    shape = (SIZE, SIZE)
    return (hit.reshape(*shape, 1).astype(np.float32), normal.reshape(*shape, 3),
            d.reshape(*shape, 3))


def test_hull_normals_of_a_sphere():
    cams = [_look_at(4.0 * np.array([np.cos(a), np.sin(a), z]), f"c{i:02d}")
            for i, (a, z) in enumerate([(a, z) for z in (-0.4, 0.4)
                                        for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)])]
    seen = [_sphere(c) for c in cams]
    out = hull_normals(cams, [m for m, _, _ in seen], np.zeros(3), 4.0)
    assert out is not None and len(out) == len(cams)
    cos, facing = [], []
    for (matte, truth, ray), (prior, conf) in zip(seen, out):
        assert prior.shape == (SIZE, SIZE, 3) and conf.shape == (SIZE, SIZE)
        assert (conf >= 0).all() and (conf <= HULL_CONFIDENCE).all()
        has = (conf > 0) & (matte[..., 0] > 0)
        assert (np.linalg.norm(prior[conf <= 0], axis=-1) == 0).all()  # no normal, no weight
        cos.append((prior * truth).sum(-1)[has])
        facing.append(-(prior * ray).sum(-1)[conf > 0])
    cos, facing = np.concatenate(cos), np.concatenate(facing)
    assert len(cos) > 0.8 * sum(m.sum() for m, _, _ in seen)  # most of the sphere has a prior
    low = np.percentile(cos, 5)
    assert cos.mean() > 0.97 and low > 0.9, (cos.mean(), low)
    assert np.percentile(facing, 1) > -0.1  # what a camera sees of the hull faces it
