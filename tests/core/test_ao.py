"""Ambient occlusion baking: per-Gaussian visibility and per-view AO maps."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.ao import _filter, ao_map, filter_torch, init_visibility, map_scale, scaled_camera
from core.config import AOConfig
from core.config import LearningRates
from core.model import GaussianModel
from core.render import RenderCamera
from core.synth.generate import look_at


def _plane_params(xs, ys, z_of, normal, spacing):
    """Thin discs tiling a patch; positions from a grid, all with one unit normal."""
    gx, gy = torch.meshgrid(xs, ys, indexing="ij")
    pts = z_of(gx.reshape(-1), gy.reshape(-1))
    n = pts.shape[0]
    z = torch.tensor([0.0, 0.0, 1.0])
    axis = torch.linalg.cross(z, normal)
    angle = math.atan2(float(axis.norm()), float(z @ normal))
    axis = axis / axis.norm() if float(axis.norm()) > 0 else torch.tensor([1.0, 0.0, 0.0])
    q = torch.cat([torch.tensor([math.cos(angle / 2)]), axis * math.sin(angle / 2)])
    return pts, q.repeat(n, 1), torch.tensor([spacing, spacing, spacing * 0.05]).repeat(n, 1), \
        normal.repeat(n, 1)


def _corner_model() -> GaussianModel:
    """A floor (z = 0, x in [0, 2]) meeting a wall (x = 0) along the y axis."""
    s = 0.06
    a = torch.arange(0.0, 2.0, s)
    floor = _plane_params(a, torch.arange(-1.0, 1.0, s),
                          lambda x, y: torch.stack([x, y, torch.zeros_like(x)], -1),
                          torch.tensor([0.0, 0.0, 1.0]), s)
    wall = _plane_params(torch.arange(-1.0, 1.0, s), torch.arange(0.0, 1.5, s),
                         lambda y, z: torch.stack([torch.zeros_like(y), y, z], -1),
                         torch.tensor([1.0, 0.0, 0.0]), s)
    means, quats, scales, normals = (torch.cat([f, w]) for f, w in zip(floor, wall))
    model = GaussianModel.from_points(means)
    n = means.shape[0]
    p = model.params
    with torch.no_grad():
        p["quats"].copy_(quats)
        p["scales"].copy_(scales.log())
        p["normals"].copy_(normals)
        p["opacity_g"].fill_(math.log(0.95 / 0.05))
        p["opacity_c"].fill_(math.log(0.95 / 0.05))
    model.n_floor = floor[0].shape[0]
    assert len(model) == n
    return model


def test_visibility_is_lower_in_the_corner():
    model = _corner_model()
    opt = model.make_optimizer(LearningRates(), 2.0)
    before = model.params["visibility"]
    vis = init_visibility(model, opt, AOConfig(n_dirs=64))
    floor_x = model.means[: model.n_floor, 0]
    near, far = vis[: model.n_floor][floor_x < 0.15], vis[: model.n_floor][floor_x > 1.5]
    # Far from the wall the floor sees its whole sky; next to it about half.
    assert float(far.mean()) > 0.9
    assert float(near.mean()) < 0.75
    assert torch.allclose(model.visibility[:, 0], vis.clamp(1e-4, 1 - 1e-4), atol=1e-5)
    assert model.params["visibility"] is not before
    assert any(p is model.params["visibility"] for g in opt.param_groups for p in g["params"])


def _look_at(eye, target) -> torch.Tensor:
    return torch.tensor(look_at(eye, target, (0.0, 0.0, 1.0)), dtype=torch.float32)


def test_ao_map_darkens_the_corner():
    model = _corner_model()
    w = h = 64
    f = 40.0
    K = torch.tensor([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    cam = RenderCamera(_look_at((2.2, 0.0, 1.2), (0.5, 0.0, 0.2)), K, w, h)
    ao = ao_map(model, cam, config=AOConfig(n_dirs=32))
    assert ao.shape == (h, w, 1)
    assert float(ao.min()) >= 0.0 and float(ao.max()) <= 1.0
    # The corner line (x = 0, z = 0) projects above the image centre, the near floor (x = 1.3)
    # below it. The corner is darker.
    corner = torch.tensor([0.0, 0.0, 0.02, 1.0]) @ cam.viewmat.T
    uc, vc = (K @ corner[:3] / corner[2])[:2].round().long().tolist()
    near = torch.tensor([1.3, 0.0, 0.0, 1.0]) @ cam.viewmat.T
    un, vn = (K @ near[:3] / near[2])[:2].round().long().tolist()
    assert float(ao[vc, uc]) < float(ao[vn, un]) - 0.1, (float(ao[vc, uc]), float(ao[vn, un]))


def test_scaled_camera_keeps_pixel_centres():
    K = torch.tensor([[50.0, 0.0, 32.0], [0.0, 55.0, 24.0], [0.0, 0.0, 1.0]])
    cam = RenderCamera(torch.eye(4), K, 64, 48)
    small = scaled_camera(cam, 0.25)
    assert (small.width, small.height) == (16, 12)
    p = torch.tensor([0.3, -0.2, 2.0])
    full = (K @ p / p[2])[:2]
    part = (small.K @ p / p[2])[:2]
    assert torch.allclose(part, full * 0.25, atol=1e-5)


def test_baker_traces_everything_at_once_like_its_parts():
    """The baker traces the Gaussians' rays and every view's map in one call (one tree); that
    gives what `init_visibility` and `ao_map` give one at a time."""
    from core.ao import GaussianAOBaker

    w = h = 48
    K = torch.tensor([[30.0, 0.0, w / 2], [0.0, 30.0, h / 2], [0.0, 0.0, 1.0]])
    cams = [RenderCamera(_look_at(eye, (0.5, 0.0, 0.2)), K, w, h)
            for eye in ((2.2, 0.0, 1.2), (1.5, 1.5, 1.0), (2.0, -1.0, 0.6))]
    cfg = AOConfig(n_dirs=16)
    apart = _corner_model()
    own = init_visibility(apart, None, cfg)
    maps = [ao_map(apart, cam, beta=0.3, config=cfg) for cam in cams]
    together = _corner_model()
    baked = GaussianAOBaker(cfg)(together, cams, None, beta=0.3)
    torch.testing.assert_close(together.visibility[:, 0], own.clamp(1e-4, 1 - 1e-4), atol=1e-6,
                               rtol=0)
    for a, b in zip(maps, baked):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=0)


@pytest.mark.parametrize("shape,sigmas", [((37, 53), (0.2, 2.0)), ((64, 48), (0.5, 1.0)),
                                          ((5, 40), (0.2, 2.0))])
def test_torch_joint_bilateral_filter_is_opencvs(shape, sigmas):
    """The device's filter (no OpenCV contrib needed, runs on the GPU) is OpenCV's, border and
    disc included, on random AO and a guide with flat and noisy parts."""
    cv2 = pytest.importorskip("cv2")
    if not hasattr(cv2, "ximgproc"):
        pytest.skip("OpenCV without its contrib modules")
    rng = np.random.default_rng(sum(shape))
    ao = rng.random(shape).astype(np.float32)
    guide = rng.normal(size=shape + (3,)).astype(np.float32)
    guide /= np.linalg.norm(guide, axis=-1, keepdims=True)
    guide[: shape[0] // 2] = guide[0, 0]
    cfg = AOConfig(sigma_color=sigmas[0], sigma_space=sigmas[1])
    ref = _filter(ao, guide, cfg)
    out = filter_torch(torch.from_numpy(ao), torch.from_numpy(guide), cfg).numpy()
    assert np.abs(out - ref).max() < 1e-5


def test_large_views_trace_a_map_of_at_most_max_map_pixels():
    K = torch.tensor([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]])
    big = RenderCamera(torch.eye(4), K, 1920, 1080)
    small = RenderCamera(torch.eye(4), K, 64, 48)
    cfg = AOConfig(scale=0.25, max_map_pixels=65_536)
    s = map_scale(big, cfg)
    assert s < 0.25 and abs(1920 * 1080 * s * s - 65_536) < 1
    cam = scaled_camera(big, s)
    assert cam.width * cam.height <= 65_536 * 1.01
    assert map_scale(small, cfg) == 0.25  # small views keep the configured scale
    assert map_scale(big, AOConfig(scale=0.25, max_map_pixels=None)) == 0.25
