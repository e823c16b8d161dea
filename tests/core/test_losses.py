"""Losses of docs/design.md section 5 on inputs with known answers."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from core.config import LossWeights
from core.losses import (
    sparsity_loss,
    depth_normal_consistency,
    depth_to_normals,
    depth_to_points,
    geometry_mask_loss,
    normal_prior_loss,
    photometric_loss,
    ssim,
    ssim_reference,
    visibility_loss,
)
from core.model import GaussianModel
from core.render import RenderCamera, render


def naive_ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Direct per-pixel SSIM, zero padding outside the image, 11x11 Gaussian sigma 1.5."""
    x = np.arange(11) - 5.0
    g = np.exp(-x * x / (2 * 1.5**2))
    g /= g.sum()
    w = np.outer(g, g)
    h, wd, c = a.shape
    pa, pb = np.pad(a, ((5, 5), (5, 5), (0, 0))), np.pad(b, ((5, 5), (5, 5), (0, 0)))
    total = 0.0
    for i in range(h):
        for j in range(wd):
            for k in range(c):
                A, B = pa[i:i + 11, j:j + 11, k], pb[i:i + 11, j:j + 11, k]
                ma, mb = (w * A).sum(), (w * B).sum()
                va, vb = (w * A * A).sum() - ma**2, (w * B * B).sum() - mb**2
                cov = (w * A * B).sum() - ma * mb
                total += ((2 * ma * mb + 1e-4) * (2 * cov + 9e-4)) / (
                    (ma**2 + mb**2 + 1e-4) * (va + vb + 9e-4))
    return total / (h * wd * c)


def test_ssim_matches_direct_formula():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(9, 12, 3, generator=g, dtype=torch.float64)
    b = (a + 0.2 * torch.rand(9, 12, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    assert ssim(a, b).item() == pytest.approx(naive_ssim(a.numpy(), b.numpy()), abs=1e-6)
    assert ssim(a, a).item() == pytest.approx(1.0, abs=1e-9)
    with pytest.raises(ValueError, match="a, b"):
        ssim(a, b[:, :5])


@pytest.mark.parametrize("shape", [(9, 12, 3), (31, 17, 1), (4, 5, 3)])
def test_separable_ssim_matches_the_2d_window_forward_and_backward(shape):
    """`ssim` blurs with two 1D passes over the five stacked maps; `ssim_reference` with the
    11x11 window (five 2D convolutions). Zero padding keeps them equal: forward and gradients
    to float64 rounding (also on images smaller than the window), float32 within 1e-6."""
    g = torch.Generator().manual_seed(sum(shape))
    a = torch.rand(shape, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(shape, generator=g, dtype=torch.float64, requires_grad=True)
    fast, ref = ssim(a, b), ssim_reference(a, b)
    assert abs(float((fast - ref).detach())) < 1e-12
    ga = torch.autograd.grad(fast, (a, b))
    gr = torch.autograd.grad(ref, (a, b))
    for x, y in zip(ga, gr):
        torch.testing.assert_close(x, y, atol=1e-13, rtol=0)
    a32, b32 = a.detach().float().requires_grad_(), b.detach().float()
    torch.testing.assert_close(ssim(a32, b32), ssim_reference(a32, b32), atol=1e-6, rtol=0)
    small = (a.detach()[:4, :5, :1].clone().requires_grad_(),
             b.detach()[:4, :5, :1].clone().requires_grad_())
    assert torch.autograd.gradcheck(ssim, small)


def test_photometric_loss_known_values():
    g = torch.Generator().manual_seed(1)
    img = torch.rand(16, 16, 3, generator=g)
    assert photometric_loss(img, img).item() == pytest.approx(0.0, abs=1e-6)
    other = (img + 0.1).clamp(max=1.0)
    expect = 0.8 * (other - img).abs().mean() + 0.2 * (1 - ssim(other, img))
    assert photometric_loss(other, img).item() == pytest.approx(expect.item(), rel=1e-6)
    pred = img.clone().requires_grad_()
    photometric_loss(pred, torch.rand(16, 16, 3, generator=g)).backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0


def test_normal_prior_loss_known_values():
    n = torch.nn.functional.normalize(torch.randn(10, 10, 3), dim=-1)
    assert normal_prior_loss(torch.zeros(10, 10, 3) + n[0, 0], n[0, 0].expand(10, 10, 3)).item() \
        == pytest.approx(0.0, abs=1e-7)
    # Constant maps: smoothness 0, L1 = 0.2 * mean |N - prior|.
    pred = torch.full((10, 10, 3), 0.5)
    prior = torch.tensor([0.0, 0.0, 1.0]).expand(10, 10, 3)
    assert normal_prior_loss(pred, prior).item() == pytest.approx(0.2 * (0.5 + 0.5 + 0.5) / 3)
    # Pixels without a prior (zero vectors) do not count.
    holes = prior.clone()
    holes[:, :5] = 0
    assert normal_prior_loss(pred, holes).item() == pytest.approx(0.2 * 0.5)
    # A confidence weighs each pixel (the rig's priors). absolute: the means stay over the
    # pixels (pairs) with a prior.
    absolute = LossWeights(normal_confidence="absolute")
    off = torch.tensor([0.0, 1.0, 0.0]).expand(10, 10, 3).clone()
    off[:, :5] = torch.tensor([0.0, 0.0, 1.0])  # the left half agrees with the prior
    sure = torch.ones(10, 10, 1)
    sure[:, 5:] = 0.25
    l1 = (0.25 * 50 * 2 / 3) / 100
    # smoothness: the jump between the halves (2/3 a channel) weighs 1 x 0.25 in each of the
    # 10 rows, out of 90 horizontal pairs; no vertical pair differs
    expected = 0.2 * l1 + 0.05 * (10 * 2 / 3 * 0.25) / 90
    assert normal_prior_loss(off, prior, weights=absolute, confidence=sure).item() \
        == pytest.approx(expected)
    # A view all of half confidence pulls half as hard as a sure one.
    half = normal_prior_loss(off, prior, weights=absolute,
                             confidence=torch.full((10, 10, 1), 0.5))
    assert half.item() == pytest.approx(0.5 * normal_prior_loss(off, prior).item(), rel=1e-6)
    # per_view: the weighted means, a pair weighed by the product; a view all of half
    # confidence pulls as hard as a sure one
    assert LossWeights().normal_confidence == "by_source"  # without a source map: per_view
    l1 = (0.25 * 50 * 2 / 3) / (50 + 0.25 * 50)
    expected = 0.2 * l1 + 0.05 * (10 * 2 / 3 * 0.25) / 45  # a row's pairs: 4 + 0.25 + 4 / 16
    assert normal_prior_loss(off, prior, confidence=sure).item() == pytest.approx(expected)
    assert normal_prior_loss(off, prior, confidence=torch.full((10, 10, 1), 0.5)
                             ).item() == pytest.approx(normal_prior_loss(off, prior).item())
    sure[:, 5:] = 0.0  # confidence 0: no prior there, under either weighing
    for weights in (absolute, LossWeights()):
        assert normal_prior_loss(off, prior, weights=weights, confidence=sure).item() \
            == pytest.approx(0.0, abs=1e-7)
    # Edge-aware: the same jump in N costs less where the prior has an edge there too.
    jump = torch.zeros(10, 10, 3)
    jump[:, 5:] = 1.0
    flat_prior = torch.full((10, 10, 3), 0.5)
    edge_prior = flat_prior.clone()
    edge_prior[:, 5:] = 1.5
    smooth_flat = normal_prior_loss(jump + 0.5, flat_prior) - 0.2 * (jump.mean())
    assert normal_prior_loss(jump + 0.5, edge_prior) < smooth_flat
    pred = torch.randn(10, 10, 3, requires_grad=True)
    normal_prior_loss(pred, n, mask=torch.ones(10, 10, 1)).backward()
    assert torch.isfinite(pred.grad).all()


def _prior_loss_by_hand(normal, prior, confidence, measured, mode):
    """The prior term written pixel by pixel and pair by pair: a pixel measured under
    `by_source` (or any under `per_view`) is weighed and counted by its confidence, any other
    weighed by it and counted as one; a pair of two per-view pixels by the product of theirs,
    any other pair weighed by the lesser and counted as one."""
    h, w = normal.shape[:2]
    ok = [[bool(prior[i, j].abs().sum() > 0) and float(confidence[i, j]) > 0 for j in range(w)]
          for i in range(h)]

    def counted_per_view(i, j):
        return mode == "per_view" or (mode == "by_source" and float(measured[i, j]) > 0.5)

    num, den = 0.0, 0.0
    for i in range(h):
        for j in range(w):
            if ok[i][j]:
                c = confidence[i, j, 0]
                num = num + (normal[i, j] - prior[i, j]).abs().mean() * c
                den += float(c) if counted_per_view(i, j) else 1.0
    l1 = num / max(den, 1.0)
    smooth = 0.0
    for di, dj in ((0, 1), (1, 0)):
        num, den = 0.0, 0.0
        for i in range(h - di):
            for j in range(w - dj):
                p, q = (i, j), (i + di, j + dj)
                if not (ok[p[0]][p[1]] and ok[q[0]][q[1]]):
                    continue
                g = (normal[q] - normal[p]).abs().mean()
                edge = torch.exp(-(prior[q] - prior[p]).abs().mean())
                cp, cq = float(confidence[p]), float(confidence[q])
                if counted_per_view(*p) and counted_per_view(*q):
                    num, den = num + g * edge * cp * cq, den + cp * cq
                else:
                    num, den = num + g * edge * min(cp, cq), den + 1.0
        smooth = smooth + num / max(den, 1.0)
    return 0.2 * l1 + 0.05 * smooth


@pytest.mark.parametrize("mode", ["per_view", "absolute", "by_source"])
def test_confidence_weighings_against_a_loop(mode):
    """Each weighing of the prior's confidence, forward and backward, against the same term
    written with loops (random maps with holes, zero confidences and both sources)."""
    g = torch.Generator().manual_seed(3)
    h, w = 7, 6
    prior = torch.nn.functional.normalize(torch.randn(h, w, 3, generator=g, dtype=torch.float64),
                                          dim=-1)
    prior[0, :3] = 0.0  # no prior
    confidence = torch.rand(h, w, 1, generator=g, dtype=torch.float64)
    confidence[4, 2:] = 0.0
    measured = (torch.rand(h, w, 1, generator=g) > 0.4).double()
    base = torch.randn(h, w, 3, generator=g, dtype=torch.float64)
    a = base.clone().requires_grad_(True)
    loss = normal_prior_loss(a, prior, weights=LossWeights(normal_confidence=mode),
                             confidence=confidence, measured=measured)
    loss.backward()
    b = base.clone().requires_grad_(True)
    ref = _prior_loss_by_hand(b, prior, confidence, measured, mode)
    ref.backward()
    torch.testing.assert_close(loss, ref)
    torch.testing.assert_close(a.grad, b.grad)


def test_by_source_is_each_weighing_where_its_source_is_alone():
    """All measured (a capture with no mattes, so no hull: the Panoptic twin, the fox), the
    weighing by source is `per_view` bit for bit; none measured (the hull's alone), `absolute`;
    without a source map, `per_view`."""
    g = torch.Generator().manual_seed(5)
    prior = torch.nn.functional.normalize(torch.randn(12, 9, 3, generator=g), dim=-1)
    confidence = torch.rand(12, 9, 1, generator=g)
    confidence[3:5] = 0.0
    by_source = LossWeights(normal_confidence="by_source")
    pred = torch.randn(12, 9, 3, generator=g)
    cases = [(torch.ones(12, 9, 1), "per_view"),
             ((confidence > 0).float(), "per_view"),  # the rig's map of a capture without mattes
             (None, "per_view"),
             (torch.zeros(12, 9, 1), "absolute")]
    for measured, mode in cases:
        a = pred.clone().requires_grad_(True)
        b = pred.clone().requires_grad_(True)
        got = normal_prior_loss(a, prior, weights=by_source, confidence=confidence,
                                measured=measured)
        want = normal_prior_loss(b, prior, weights=LossWeights(normal_confidence=mode),
                                 confidence=confidence)
        got.backward()
        want.backward()
        assert torch.equal(got, want) and torch.equal(a.grad, b.grad)


def rotation(axis: list[float], angle: float) -> torch.Tensor:
    a = torch.nn.functional.normalize(torch.tensor(axis, dtype=torch.float64), dim=0)
    k = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def plane_view(h: int = 20, w: int = 24):
    """Depth of the camera-space plane n.X = -d (n facing the camera) and the world normal."""
    K = torch.tensor([[30.0, 0, 12.3], [0, 28.0, 9.7], [0, 0, 1]], dtype=torch.float64)
    R = rotation([0.3, -1.0, 0.5], 0.7)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = torch.tensor([0.2, -0.4, 1.0], dtype=torch.float64)
    n_cam = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64),
                                          dim=0)
    v, u = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    depth = (-3.0 / (rays.double() @ n_cam))[..., None]
    return depth, K, viewmat, R.T @ n_cam


def test_back_projection_returns_world_points():
    depth, K, viewmat, _ = plane_view()
    pts = depth_to_points(depth, K, viewmat)
    cam = pts @ viewmat[:3, :3].T + viewmat[:3, 3]
    torch.testing.assert_close(cam[..., 2:], depth)
    uv = (cam @ K.T)[..., :2] / cam[..., 2:]
    torch.testing.assert_close(uv[3, 5], torch.tensor([5.5, 3.5], dtype=torch.float64))


def test_plane_gives_the_minimum_of_the_consistency_term():
    depth, K, viewmat, n_world = plane_view()
    n_d = depth_to_normals(depth, K, viewmat)
    torch.testing.assert_close(n_d, n_world.expand_as(n_d), atol=1e-6, rtol=0)
    alpha = torch.full_like(depth, 0.8)
    good = depth_normal_consistency(0.8 * n_world.expand(20, 24, 3), depth, alpha, K, viewmat)
    assert good.item() == pytest.approx(0.0, abs=1e-8)
    flipped = depth_normal_consistency(-0.8 * n_world.expand(20, 24, 3), depth, alpha, K, viewmat)
    assert flipped.item() == pytest.approx(0.01 * 1.6, rel=1e-6)
    n_tilt = rotation([1, 0, 0], 0.3) @ n_world
    tilted = depth_normal_consistency(0.8 * n_tilt.expand(20, 24, 3), depth, alpha, K, viewmat)
    expect = 0.01 * 0.8 * (1 - float(n_tilt @ n_world))
    assert expect > 1e-4 and tilted.item() == pytest.approx(expect, rel=1e-4)


def test_consistency_of_a_rendered_plane():
    # A dense layer of flat Gaussians at z = 3 facing the camera: N = O_g (0, 0, -1) = n(D) O_g.
    ax = torch.linspace(-2.6, 2.6, 25)
    y, x = torch.meshgrid(ax, ax, indexing="ij")
    pts = torch.stack([x.reshape(-1), y.reshape(-1), torch.full((625,), 3.0)], dim=-1)
    m = GaussianModel.from_points(pts)
    with torch.no_grad():
        m.params["scales"][:, 2] = math.log(1e-3)
        m.params["opacity_c"].fill_(2.0)
        m.params["opacity_g"].fill_(2.0)
        m.params["normals"].copy_(torch.tensor([[0.0, 0.0, -1.0]]))
    cam = RenderCamera(torch.eye(4), torch.tensor([[20.0, 0, 16], [0, 20.0, 16], [0, 0, 1]]),
                       32, 32)
    r = render(m, cam, sh_degree=0, beta=0.5)
    assert (r.alpha_g > 0.5).float().mean() > 0.5
    loss = depth_normal_consistency(r.normal, r.depth, r.alpha_g, cam.K, cam.viewmat)
    assert -1e-6 < loss.item() < 1e-4
    with torch.no_grad():
        m.params["normals"].copy_(torch.tensor([[0.0, 1.0, -1.0]]))
    r2 = render(m, cam, sh_degree=0, beta=0.5)
    worse = depth_normal_consistency(r2.normal, r2.depth, r2.alpha_g, cam.K, cam.viewmat)
    assert worse.item() > loss.item() + 1e-3
    worse.backward()
    for name in ("normals", "means", "opacity_g"):
        assert torch.isfinite(m.params[name].grad).all(), name
    assert m.params["normals"].grad.abs().sum() > 0


def test_consistency_gradients_are_finite_on_empty_pixels():
    depth = torch.zeros(8, 8, 1)
    depth[2:6, 2:6] = 2.0
    depth.requires_grad_()
    normal = torch.randn(8, 8, 3, requires_grad=True)
    alpha = (depth.detach() > 0).float()
    K, V = torch.tensor([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]]), torch.eye(4)
    depth_normal_consistency(normal, depth, alpha, K, V).backward()
    assert torch.isfinite(depth.grad).all() and torch.isfinite(normal.grad).all()


def test_visibility_loss_known_values():
    v = torch.full((6, 6, 1), 0.5, requires_grad=True)
    assert visibility_loss(v, torch.full((6, 6, 1), 0.5)).item() == pytest.approx(0.0)
    assert visibility_loss(v, torch.full((6, 6, 1), 0.3)).item() == pytest.approx(0.02)
    stripes = torch.zeros(6, 6, 1)
    stripes[:, ::2] = 1.0
    # L1 0 against itself; smoothness: mean |dx| = 1, mean |dy| = 0.
    assert visibility_loss(stripes, stripes).item() == pytest.approx(0.01)
    visibility_loss(v, torch.rand(6, 6, 1), mask=torch.ones(6, 6, 1)).backward()
    assert torch.isfinite(v.grad).all()
    with pytest.raises(ValueError, match="visibility, target"):
        visibility_loss(v, torch.zeros(5, 6, 1))
    # The paper's Eq. 10: the smoothness weighted by exp(-|grad N_prior|). Prior normals that
    # flip between +z and -z at every column (channel mean |dx| = 2/3) leave exp(-2/3) of it;
    # a flat prior leaves it whole.
    flip = torch.zeros(6, 6, 3)
    flip[..., 2] = 1.0
    flip[:, ::2, 2] = -1.0
    assert visibility_loss(stripes, stripes, prior=flip).item() == pytest.approx(
        0.01 * math.exp(-2 / 3))
    flat = torch.zeros(6, 6, 3)
    flat[..., 2] = 1.0
    assert visibility_loss(stripes, stripes, prior=flat).item() == pytest.approx(0.01)
    with pytest.raises(ValueError, match="prior"):
        visibility_loss(stripes, stripes, prior=torch.zeros(5, 6, 3))


def test_geometry_mask_loss_known_values():
    alpha = torch.zeros(4, 4, 1, requires_grad=True)
    mask = torch.zeros(4, 4, 1)
    mask[:2] = 1.0  # half the image is the subject
    # 1.0 * mean |0 - mask| = 0.5
    assert geometry_mask_loss(alpha, mask).item() == pytest.approx(0.5)
    assert geometry_mask_loss(mask.clone(), mask).item() == pytest.approx(0.0)
    floater = mask.clone()
    floater[3, 3] = 0.8  # geometry in the background costs its coverage
    assert geometry_mask_loss(floater, mask).item() == pytest.approx(0.8 / 16)
    geometry_mask_loss(alpha, mask).backward()
    assert (alpha.grad[:2] < 0).all() and (alpha.grad[2:] == 0).all()
    with pytest.raises(ValueError, match="alpha, mask"):
        geometry_mask_loss(alpha, torch.zeros(4, 3, 1))


def test_sparsity_loss_known_values_and_gradients():
    """3DGS-MCMC's regularizers: w_o * sum of the mean opacities + w_s * mean scale / extent,
    checked against the analytic values and gradients; zero weights are an exact 0."""
    o_c = torch.tensor([0.2, 0.6], requires_grad=True)
    o_g = torch.tensor([0.1, 0.3], requires_grad=True)
    scales = torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]], requires_grad=True)
    off = sparsity_loss([o_c, o_g], scales, 2.0)
    assert off.item() == 0.0 and not off.requires_grad
    w = replace(LossWeights(), opacity_l1=0.01, scale_l1=0.02)
    loss = sparsity_loss([o_c, o_g], scales, 2.0, w)
    # 0.01 * (0.4 + 0.2) + 0.02 * 0.35 / 2
    assert loss.item() == pytest.approx(0.006 + 0.0035)
    loss.backward()
    assert torch.allclose(o_c.grad, torch.full((2,), 0.01 / 2))
    assert torch.allclose(o_g.grad, torch.full((2,), 0.01 / 2))
    assert torch.allclose(scales.grad, torch.full((2, 3), 0.02 / 6 / 2.0))
    with pytest.raises(ValueError, match="extent"):
        sparsity_loss([o_c], scales, 0.0, w)
