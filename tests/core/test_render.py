"""Rendering: SH evaluation, camera conversion, the Render fields against known single-Gaussian
images and against the dense reference rasterizer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.data import Camera
from core.model import GaussianModel
from core.render import RenderCamera, eval_sh, render, safe_divide, sh_basis


def fibonacci_sphere(n: int) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    r = torch.sqrt(1 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def test_sh_basis_is_orthonormal():
    dirs = fibonacci_sphere(20000)
    Y = sh_basis(dirs, 3)
    gram = (Y.T @ Y) * (4 * math.pi / dirs.shape[0])
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=2e-3, rtol=0)


def test_sh_signs_match_3dgs():
    # 3DGS: result = C0 sh0 - C1 y sh1 + C1 z sh2 - C1 x sh3.
    d = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    Y = sh_basis(d, 1)
    c1 = 0.4886025119029199
    torch.testing.assert_close(Y[:, 1:], torch.tensor([[0, 0, -c1], [-c1, 0, 0], [0, c1, 0]]))
    sh = torch.zeros(3, 16, 3)
    sh[:, 0] = 1.0
    torch.testing.assert_close(eval_sh(sh, d, 3), torch.full((3, 3), 0.28209479177387814))
    with pytest.raises(ValueError, match="degree"):
        sh_basis(d, 4)
    with pytest.raises(ValueError, match="sh"):
        eval_sh(torch.zeros(3, 4, 3), d, 2)


def test_render_camera_from_capture_camera():
    w2c = np.eye(4)
    w2c[:3, 3] = [0.5, -1.0, 2.0]
    cam = Camera("c", 16, 8, np.diag([10.0, 10.0, 1.0]), w2c, None)
    rc = RenderCamera.from_camera(cam)
    assert rc.viewmat.dtype == torch.float32 and (rc.width, rc.height) == (16, 8)
    torch.testing.assert_close(rc.center, torch.tensor([-0.5, 1.0, -2.0]))


def one_gaussian(opacity_c: float = 0.8, opacity_g: float = 0.1) -> GaussianModel:
    m = GaussianModel.from_points(torch.tensor([[0.0, 0.0, 4.0]]), torch.tensor([[0.9, 0.2, 0.4]]))
    with torch.no_grad():
        m.params["scales"].copy_(torch.log(torch.tensor([[0.3, 0.3, 0.01]])))
        m.params["opacity_c"].fill_(math.log(opacity_c / (1 - opacity_c)))
        m.params["opacity_g"].fill_(math.log(opacity_g / (1 - opacity_g)))
        m.params["normals"].copy_(torch.tensor([[0.0, 0.0, -2.0]]))  # not unit: normalized
        m.params["visibility"].fill_(math.log(0.7 / 0.3))
    return m


def camera(size: int = 17) -> RenderCamera:
    # The principal point sits on pixel (8, 8)'s centre, where the Gaussian projects.
    K = torch.tensor([[20.0, 0, size / 2], [0, 20.0, size / 2], [0, 0, 1]])
    return RenderCamera(torch.eye(4), K, size, size)


def test_single_gaussian_fields():
    m = one_gaussian()
    r = render(m, camera(), sh_degree=0, beta=1.0, antialiased=False,
               background=torch.tensor([0.0, 0.0, 1.0]))
    # beta = 1: each branch sees its own opacity; at the centre alpha = opacity.
    assert r.alpha_c[8, 8, 0].item() == pytest.approx(0.8, abs=1e-4)
    assert r.alpha_g[8, 8, 0].item() == pytest.approx(0.1, abs=1e-4)
    expect = torch.tensor([0.9 * 0.8, 0.2 * 0.8, 0.4 * 0.8 + 0.2])
    torch.testing.assert_close(r.rgb[8, 8], expect, atol=1e-4, rtol=0)
    torch.testing.assert_close(r.normal[8, 8], torch.tensor([0.0, 0.0, -0.1]), atol=1e-4, rtol=0)
    assert r.visibility[8, 8, 0].item() == pytest.approx(0.07, abs=1e-4)
    assert r.depth[8, 8, 0].item() == pytest.approx(4.0, abs=1e-4)  # expected, not alpha-weighted
    assert r.depth[0, 0, 0].item() == 0.0  # nothing drawn there: safe divide gives 0
    assert r.raster.radii[0] > 0


def test_tied_opacity_and_appearance_only_pass():
    m = one_gaussian()
    untied = render(m, camera(), sh_degree=0, beta=0.0, geometry=False, antialiased=False)
    tied = render(m, camera(), sh_degree=0, beta=0.0, geometry=False, tie_opacity=True,
                  antialiased=False)
    assert untied.alpha_c[8, 8, 0].item() == pytest.approx(0.45, abs=1e-4)  # (0.8 + 0.1) / 2
    assert tied.alpha_c[8, 8, 0].item() == pytest.approx(0.8, abs=1e-4)
    assert torch.all(tied.normal == 0) and torch.all(tied.alpha_g == 0)
    assert tied.raster.geometry.shape == (17, 17, 0)


def random_scene(n: int = 40, seed: int = 0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(n, 3, generator=g) * 0.4 + torch.tensor([0.0, 0.0, 3.0])
    m = GaussianModel.from_points(pts, torch.rand(n, 3, generator=g))
    with torch.no_grad():
        for name in ("shN", "normals", "quats"):
            m.params[name].copy_(torch.randn(m.params[name].shape, generator=g) * 0.5)
        m.params["quats"][:, 0] += 1.0
        m.params["opacity_c"].copy_(torch.randn(n, generator=g))
        m.params["opacity_g"].copy_(torch.randn(n, generator=g))
    return m


def test_native_matches_reference_and_gradients_reach_every_parameter():
    m = random_scene()
    cam = RenderCamera(torch.eye(4), torch.tensor([[30.0, 0, 12], [0, 30.0, 12], [0, 0, 1]]),
                       24, 24)
    outs = {b: render(m, cam, sh_degree=3, beta=0.4, backend=b) for b in ("native", "reference")}
    for field in ("rgb", "normal", "depth", "visibility", "alpha_c", "alpha_g"):
        torch.testing.assert_close(getattr(outs["native"], field),
                                   getattr(outs["reference"], field), atol=2e-4, rtol=1e-3)
    r = outs["native"]
    (r.rgb.sum() + r.normal.sum() + r.depth.sum() + r.visibility.sum()).backward()
    for name, p in m.params.items():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name
    assert r.raster.absgrad_c.sum() > 0 and r.raster.absgrad_g.sum() > 0


def test_safe_divide_has_finite_gradients():
    num = torch.tensor([1.0, 2.0], requires_grad=True)
    den = torch.tensor([0.0, 4.0], requires_grad=True)
    out = safe_divide(num, den)
    out.sum().backward()
    torch.testing.assert_close(out.detach(), torch.tensor([0.0, 0.5]))
    assert torch.isfinite(num.grad).all() and torch.isfinite(den.grad).all()


def test_the_near_plane_hides_a_gaussian_between_the_old_plane_and_the_rigs():
    # At depth 0.05: past the rasterizer's 0.01, before a rig's plane at 0.1. Close to the
    # camera it covers the whole view (a dome's wall beside a camera); the rig's plane drops it.
    m = one_gaussian()
    with torch.no_grad():
        m.params["means"].copy_(torch.tensor([[0.0, 0.0, 0.05]]))
        m.params["scales"].copy_(torch.log(torch.tensor([[0.01, 0.01, 0.001]])))
    near = camera()
    assert near.near == 0.01
    seen = render(m, near, sh_degree=0, antialiased=False)
    far = RenderCamera(near.viewmat, near.K, near.width, near.height, 0.1)
    clipped = render(m, far, sh_degree=0, antialiased=False)
    assert seen.alpha_c[8, 8, 0] > 0.4 and seen.raster.radii[0] > 0  # (0.8 + 0.1) / 2
    assert torch.all(clipped.alpha_c == 0) and clipped.raster.radii[0] == 0
    assert far.to("cpu").near == 0.1  # a copy elsewhere keeps it
    with pytest.raises(ValueError, match="near"):
        RenderCamera.from_camera(Camera("c", 8, 8, np.eye(3), np.eye(4), None), near=0.0)
