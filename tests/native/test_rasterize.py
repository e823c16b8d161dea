"""The native rasterizer against the dense PyTorch reference, forward and backward."""

from __future__ import annotations

import itertools

import pytest
import torch

from compare import compare
from native import rasterize
from scenes import random_scene

FWD_TOL = 1e-4   # float32: relative error of every output (issue: under 1e-4)
GRAD_TOL = 2e-3  # float32: relative error of every gradient (issue: under 2e-3)
EXACT_TOL = 1e-9  # float64 native against float64 reference: the same algorithm, no rounding


def assert_close(result, fwd_tol=FWD_TOL, grad_tol=GRAD_TOL):
    assert result.ambiguous <= 8, f"{result.ambiguous} ambiguous pixels: a scene too near ties"
    bad_f = {k: v for k, v in result.forward.items() if k != "radii_mismatch" and v > fwd_tol}
    bad_g = {k: v for k, v in result.grads.items() if v > grad_tol}
    assert not bad_f, f"forward outputs off: {bad_f}"
    assert not bad_g, f"gradients off: {bad_g}"
    assert result.forward["radii_mismatch"] == 0


@pytest.mark.parametrize("seed,beta,antialiased",
                         list(itertools.product([0, 1, 2], [0.0, 0.3, 0.7, 1.0], [False, True])))
def test_random_scenes_match_reference(seed, beta, antialiased):
    scene = random_scene(160, 40, 32, seed=seed)
    assert_close(compare(scene, seed=seed, beta=beta, antialiased=antialiased))


@pytest.mark.parametrize("seed,beta,antialiased",
                         [(0, 0.0, False), (1, 0.3, True), (2, 0.7, False), (3, 1.0, True)])
def test_float64_native_equals_reference(seed, beta, antialiased):
    scene = random_scene(160, 40, 32, seed=seed, behind=0.1, offscreen=0.1)
    result = compare(scene, seed=seed, beta=beta, antialiased=antialiased, dtype=torch.float64,
                     background=torch.tensor([0.1, 0.2, 0.3]))
    assert_close(result, fwd_tol=EXACT_TOL, grad_tol=EXACT_TOL)


@pytest.mark.parametrize("C,G", list(itertools.product([1, 3, 8], [1, 3, 8])))
def test_channel_counts(C, G):
    scene = random_scene(120, 33, 27, C=C, G=G, seed=10 + C + G)
    assert_close(compare(scene, seed=C * G, beta=0.3, antialiased=True))


def test_many_channels_no_silent_limit():
    scene = random_scene(60, 24, 20, C=67, G=41, seed=3)
    assert_close(compare(scene, beta=0.5))


def test_dense_scene_saturates_and_stops_early():
    # Large, nearly opaque Gaussians: both branches reach T < 1e-4 and stop early.
    scene = random_scene(300, 36, 30, seed=4, scale=(0.15, 0.4), opacity=(0.85, 1.0))
    result = compare(scene, beta=0.3, antialiased=False)
    assert_close(result)
    out = rasterize(*scene.args(), beta=0.3)
    t_c, t_g = 1 - out.alpha_c, 1 - out.alpha_g
    # Stopped pixels end with T just above the floor: at least 1e-4 before the last factor.
    assert float((t_c < 1e-2).float().mean()) > 0.5
    assert float((t_g < 1e-2).float().mean()) > 0.5
    assert float(t_c.min()) >= 1e-4 and float(t_g.min()) >= 1e-4


def test_behind_camera_and_offscreen():
    scene = random_scene(200, 40, 30, seed=5, behind=0.25, offscreen=0.25)
    assert_close(compare(scene, beta=0.7, antialiased=True))
    out = rasterize(*scene.args())
    assert int((out.radii[:50] > 0).sum()) == 0, "Gaussians behind the camera were drawn"
    assert int((out.radii[50:100] > 0).sum()) == 0, "off-screen Gaussians were drawn"
    assert int((out.radii[100:] > 0).sum()) > 50


def test_near_and_far_planes_cull():
    scene = random_scene(150, 32, 32, seed=6)
    assert_close(compare(scene, near=2.5, far=3.4))
    z = (scene.means @ scene.viewmat[:3, :3].T + scene.viewmat[:3, 3])[:, 2]
    out = rasterize(*scene.args(), near=2.5, far=3.4)
    assert bool((out.radii[(z <= 2.5) | (z >= 3.4)] == 0).all())


def test_background():
    scene = random_scene(100, 30, 24, seed=7)
    assert_close(compare(scene, background=torch.tensor([0.3, 0.9, 0.1]), beta=0.3))


def test_appearance_only_pass_matches_reference_and_full_pass():
    scene = random_scene(150, 32, 28, seed=8)
    assert_close(compare(scene, geometry_branch=False))
    args = list(scene.args())
    both = rasterize(*args, beta=0.0)
    args[6] = None
    rgb = rasterize(*args, beta=0.0)
    assert torch.equal(rgb.color, both.color)
    assert rgb.geometry.shape == (28, 32, 0)
    assert float(rgb.alpha_g.abs().max()) == 0.0 and float(rgb.depth.abs().max()) == 0.0


def test_absgrad_is_per_branch():
    # With beta = 1 the appearance branch sees only opacity_c: a Gaussian with opacity_c = 0 has
    # no appearance AbsGS but a geometry one.
    scene = random_scene(40, 24, 24, seed=9)
    scene.opacity_c[0] = 0.0
    scene.opacity_g[0] = 0.9
    s = scene.requires_grad_()
    out = rasterize(*s.args(), beta=1.0)
    (out.color.sum() + out.geometry.sum()).backward()
    if int(out.radii[0]) > 0:
        assert float(out.absgrad_c[0].abs().sum()) == 0.0
        assert float(out.absgrad_g[0].abs().sum()) > 0.0
    assert float(out.absgrad_c.sum()) > 0 and float(out.absgrad_g.sum()) > 0


def test_gradcheck_float64_tiny_scene():
    torch.manual_seed(0)
    scene = random_scene(6, 10, 8, seed=11, scale=(0.2, 0.5), opacity=(0.3, 0.8), C=2, G=2,
                         spread=0.5).to(torch.float64)
    bg = torch.tensor([0.2, 0.7], dtype=torch.float64)
    names = list(scene.float_tensors())
    inputs = [t.clone().requires_grad_() for t in scene.float_tensors().values()] + [
        bg.clone().requires_grad_()]

    def fn(*ts):
        kw = dict(zip(names, ts[:-1]))
        out = rasterize(kw["means"], kw["quats"], kw["scales"], kw["opacity_c"], kw["opacity_g"],
                        kw["colors"], kw["geometry"], kw["viewmat"], kw["K"], 10, 8, beta=0.4,
                        antialiased=True, background=ts[-1], eps2d=0.3)
        return out.color, out.geometry, out.depth, out.alpha_c, out.alpha_g, out.means2d

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_empty_inputs_and_zero_area_images():
    scene = random_scene(20, 16, 16, seed=12)
    args = list(scene.args())
    for w, h in [(0, 16), (16, 0), (0, 0)]:
        args[9], args[10] = w, h
        out = rasterize(*args)
        assert out.color.shape == (h, w, 3) and out.geometry.shape == (h, w, 5)
        assert int((out.radii > 0).sum()) == 0
    empty = random_scene(0, 16, 12, seed=0)
    out = rasterize(*empty.args(), background=torch.tensor([1.0, 0.5, 0.0]))
    assert out.color.shape == (12, 16, 3)
    assert torch.allclose(out.color, torch.tensor([1.0, 0.5, 0.0]).expand(12, 16, 3))
    assert float(out.alpha_c.abs().max()) == 0.0


def test_contribution_is_max_weight():
    scene = random_scene(80, 24, 24, seed=13)
    out = rasterize(*scene.args())
    assert float(out.contribution.min()) >= 0.0 and float(out.contribution.max()) <= 0.99
    assert bool((out.contribution[out.radii == 0] == 0).all())


def test_thread_count_follows_image_size_and_keeps_results():
    """Images of fewer than 384 tiles run on one thread (a second costs more than it saves);
    larger ones are split in contiguous parts with their own gradient buffers. Outputs are the
    same either way, gradients to the summation order (float64: 1e-12)."""
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            # 25 x 20 = 500 tiles: two parts with two threads
            s = random_scene(400, 400, 320, seed=5).to(torch.float64).requires_grad_()
            out = rasterize(*s.args(), beta=0.4, antialiased=True)
            loss = (out.color * torch.linspace(0, 1, 3, dtype=torch.float64)).sum() \
                + out.geometry.sum() + out.depth.sum() + out.alpha_g.sum()
            loss.backward()
            results.append((out, {k: v.grad.clone() for k, v in s.float_tensors().items()
                                  if v.grad is not None}))
    finally:
        torch.set_num_threads(before)
    (a, ga), (b, gb) = results
    for name in ("color", "geometry", "depth", "alpha_c", "alpha_g", "contribution"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), atol=0, rtol=0)
    assert ga.keys() == gb.keys() and ga
    for name in ga:
        torch.testing.assert_close(ga[name], gb[name], atol=1e-12, rtol=1e-10)
