"""The CUDA rasterizer against the CPU op, forward and backward (skipped without a GPU).

Both sides run the same algorithm on the same float values; they differ by float rounding
(nvcc contracts a*b+c into FMA, atomics add in any order). Where a blending decision (alpha
1/255, clamp 0.99, T 1e-4) lies within float32 reach of its threshold, either side may decide
the other way, so small scenes leave those pixels and Gaussians out, as the CPU tests do against
the reference (compare.ambiguous); large scenes, where the dense ambiguity test is too big, are
compared by norms. float64 on both sides leaves no ambiguity: the tolerance there is 1e-10.
"""

from __future__ import annotations

import math

import pytest
import torch

from compare import ambiguous, rel_err
from native import rasterize
from scenes import random_scene


def _cuda_ready() -> tuple[bool, str]:
    if not torch.cuda.is_available():
        return False, "no CUDA device (the CUDA kernels are tested on a GPU machine)"
    from native._backend import has_cuda

    if not has_cuda():
        return False, "the native extension was built without CUDA (nvcc missing or DGS_CUDA=0)"
    return True, ""


_READY, _WHY = _cuda_ready()
pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not _READY, reason=_WHY)]

FWD_TOL = 1e-4
GRAD_TOL = 2e-3
EXACT_TOL = 1e-10
OUTPUTS = ("color", "geometry", "depth", "alpha_c", "alpha_g", "means2d", "contribution")
GRADS = ("means", "quats", "scales", "opacity_c", "opacity_g", "colors", "geometry", "viewmat",
         "K")


def run(scene, device, dtype, *, geometry_branch=True, background=None, seed=0, **kw):
    """Outputs and gradients (on the CPU, float64) of one rasterization with a random linear loss
    on every output."""
    s = scene.to(dtype)
    tensors = {k: v.to(device).requires_grad_() for k, v in s.float_tensors().items()}
    bg = None
    if background is not None:
        bg = background.to(device=device, dtype=dtype).clone().requires_grad_()
    geometry = tensors["geometry"] if geometry_branch else None
    out = rasterize(tensors["means"], tensors["quats"], tensors["scales"], tensors["opacity_c"],
                    tensors["opacity_g"], tensors["colors"], geometry, tensors["viewmat"],
                    tensors["K"], s.width, s.height, background=bg, **kw)
    g = torch.Generator().manual_seed(seed + 7)
    loss = 0.0
    for name in ("color", "geometry", "depth", "alpha_c", "alpha_g", "means2d"):
        t = getattr(out, name)
        loss = loss + (t * torch.randn(t.shape, generator=g, dtype=torch.float64).to(t)).sum()
    loss.backward()
    result = {name: getattr(out, name).detach().double().cpu() for name in OUTPUTS}
    result["radii"] = out.radii.cpu()
    result["absgrad_c"] = out.absgrad_c.double().cpu()
    result["absgrad_g"] = out.absgrad_g.double().cpu()
    for name in GRADS:
        if name == "geometry" and not geometry_branch:
            continue
        result["grad_" + name] = tensors[name].grad.double().cpu()
    if bg is not None:
        result["grad_background"] = bg.grad.double().cpu()
    return result


def assert_match(cuda, cpu, keep_pix=None, keep_g=None, fwd_tol=FWD_TOL, grad_tol=GRAD_TOL):
    bad = {}
    n = cpu["means2d"].shape[0]
    for name, ref in cpu.items():
        got = cuda[name]
        assert got.shape == ref.shape, f"{name}: shape {tuple(got.shape)} != {tuple(ref.shape)}"
        if name == "radii":
            mismatch = int((got != ref).sum())
            if mismatch:
                bad[name] = mismatch
            continue
        if keep_pix is not None and got.dim() == 3 and got.shape[:2] == keep_pix.shape:
            got, ref = got[keep_pix], ref[keep_pix]
        elif (keep_g is not None and got.dim() and got.shape[0] == n
              and name not in ("grad_viewmat", "grad_K")):
            got, ref = got[keep_g], ref[keep_g]
        tol = grad_tol if name.startswith(("grad_", "absgrad")) else fwd_tol
        err = rel_err(got, ref)
        if not math.isfinite(err) or err > tol:
            bad[name] = err
    assert not bad, f"CUDA differs from the CPU op: {bad}"


def compare_small(scene, *, seed=0, geometry_branch=True, background=None, **kw):
    cpu = run(scene, "cpu", torch.float32, geometry_branch=geometry_branch,
              background=background, seed=seed, **kw)
    cuda = run(scene, "cuda", torch.float32, geometry_branch=geometry_branch,
               background=background, seed=seed, **kw)
    pix, gauss = ambiguous(scene.to(torch.float64), **kw)
    assert int(pix.sum()) <= 0.02 * pix.numel(), "scene too close to ties for a comparison"
    assert_match(cuda, cpu, ~pix, ~gauss)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("beta", [0.0, 0.3, 0.7, 1.0])
@pytest.mark.parametrize("antialiased", [False, True])
def test_random_scenes_match_cpu(seed, beta, antialiased):
    scene = random_scene(400, 72, 56, seed=seed, behind=0.05, offscreen=0.05)
    compare_small(scene, seed=seed, beta=beta, antialiased=antialiased)


@pytest.mark.parametrize("C,G", [(3, 1), (3, 3), (3, 4), (3, 5), (1, 2), (3, 7), (48, 9),
                                 (8, 1)])
def test_channel_paths(C, G):
    """The register paths (C = 3, G in {1, 3, 4, 5}) and the generic loop."""
    scene = random_scene(300, 48, 40, C=C, G=G, seed=C * 100 + G)
    compare_small(scene, seed=C + G, beta=0.5)


def test_appearance_only():
    scene = random_scene(300, 48, 40, seed=5)
    compare_small(scene, seed=5, geometry_branch=False)


def test_background_gradient():
    scene = random_scene(300, 48, 40, seed=6)
    compare_small(scene, seed=6, beta=0.3, background=torch.tensor([0.2, 0.5, 0.9]))


@pytest.mark.parametrize("width,height", [(37, 23), (16, 16), (1, 50), (50, 1), (17, 33)])
def test_image_sizes_not_multiples_of_the_tile(width, height):
    scene = random_scene(200, width, height, seed=width + height)
    compare_small(scene, seed=1, beta=0.4)


@pytest.mark.parametrize("seed,beta,antialiased", [(0, 0.0, False), (1, 0.3, True),
                                                   (2, 0.7, False), (3, 1.0, True)])
def test_float64_equals_cpu(seed, beta, antialiased):
    scene = random_scene(400, 64, 48, seed=seed, behind=0.1, offscreen=0.1)
    bg = torch.tensor([0.1, 0.2, 0.3])
    cpu = run(scene, "cpu", torch.float64, background=bg, beta=beta, antialiased=antialiased)
    cuda = run(scene, "cuda", torch.float64, background=bg, beta=beta, antialiased=antialiased)
    assert_match(cuda, cpu, fwd_tol=EXACT_TOL, grad_tol=EXACT_TOL)


def test_gradcheck_on_cuda():
    scene = random_scene(12, 12, 10, seed=3, scale=(0.2, 0.5), opacity=(0.1, 0.8)).to(
        torch.float64)
    tensors = [t.cuda().requires_grad_() for t in (scene.means, scene.scales, scene.opacity_c,
                                                    scene.opacity_g, scene.colors,
                                                    scene.geometry)]
    quats, viewmat, K = scene.quats.cuda(), scene.viewmat.cuda(), scene.K.cuda()

    def f(means, scales, oc, og, colors, geometry):
        out = rasterize(means, quats, scales, oc, og, colors, geometry, viewmat, K, 12, 10,
                        beta=0.3)
        return out.color, out.geometry, out.depth, out.alpha_c, out.alpha_g

    assert torch.autograd.gradcheck(f, tensors, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_intersect_equals_cpu_including_depth_ties():
    from native._wrapper import intersect_tiles

    g = torch.Generator().manual_seed(0)
    n, w, h = 5000, 300, 200
    x0 = torch.randint(-20, w, (n,), generator=g)
    y0 = torch.randint(-20, h, (n,), generator=g)
    rects = torch.stack([x0.clamp(min=0), y0.clamp(min=0),
                         (x0 + torch.randint(0, 80, (n,), generator=g)).clamp(max=w - 1),
                         (y0 + torch.randint(0, 80, (n,), generator=g)).clamp(max=h - 1)],
                        1).int()
    rects[::7] = torch.tensor([0, 0, -1, -1], dtype=torch.int32)  # not drawn
    depths = torch.rand(n, generator=g) * 10
    depths[::3] = 2.5  # ties break by index
    off_cpu, ids_cpu = intersect_tiles(rects, depths, w, h)
    off_gpu, ids_gpu = intersect_tiles(rects.cuda(), depths.cuda(), w, h)
    assert torch.equal(off_gpu.cpu(), off_cpu)
    assert torch.equal(ids_gpu.cpu(), ids_cpu)


def test_all_behind_the_camera():
    scene = random_scene(500, 64, 48, seed=1, behind=1.0)
    cuda = run(scene, "cuda", torch.float32)
    assert cuda["alpha_c"].abs().max() == 0 and cuda["alpha_g"].abs().max() == 0
    assert_match(cuda, run(scene, "cpu", torch.float32))


def test_one_huge_gaussian_covers_every_tile():
    scene = random_scene(1, 200, 150, seed=2, opacity=(0.9, 0.9))
    scene.means.zero_()
    scene.scales = torch.tensor([[3.0, 2.0, 1.0]])  # anisotropic: the rotation has a gradient
    cuda, cpu = run(scene, "cuda", torch.float32), run(scene, "cpu", torch.float32)
    assert float(cuda["alpha_c"].min()) > 0.3  # every pixel covered
    assert_match(cuda, cpu)


def test_saturated_dense_scene_stops_early():
    scene = random_scene(3000, 64, 48, seed=4, scale=(0.1, 0.4), opacity=(0.9, 1.0),
                         spread=0.3)
    compare_small(scene, seed=4, beta=0.5)


@pytest.mark.parametrize("width,height", [(0, 10), (10, 0), (0, 0)])
def test_zero_area_images(width, height):
    scene = random_scene(50, width, height, seed=0)
    scene.K = random_scene(1, 64, 48).K  # a camera with focal lengths; the image has no area
    out = rasterize(*[t.cuda() if isinstance(t, torch.Tensor) else t for t in scene.args()])
    assert out.color.shape == (height, width, 3) and out.color.is_cuda


def test_no_gaussians():
    scene = random_scene(0, 32, 24, seed=0)
    out = rasterize(*[t.cuda() if isinstance(t, torch.Tensor) else t for t in scene.args()])
    assert out.color.shape == (24, 32, 3) and float(out.alpha_c.abs().max()) == 0


def test_inputs_on_two_devices_are_refused():
    scene = random_scene(20, 16, 16, seed=0)
    args = [t.cuda() if isinstance(t, torch.Tensor) else t for t in scene.args()]
    args[7] = args[7].cpu()  # viewmat left on the CPU
    with pytest.raises((ValueError, RuntimeError), match="viewmat"):
        rasterize(*args)


def _surface_scene(n: int, width: int, height: int, seed: int):
    """n Gaussians on a wavy sheet filling the view: per-pixel depth complexity like a trained
    model's, not the random cube's."""
    g = torch.Generator().manual_seed(seed)
    scene = random_scene(n, width, height, seed=seed, opacity=(0.3, 1.0))
    uv = torch.rand(n, 2, generator=g) * 2 - 1
    scene.means = torch.stack([uv[:, 0] * 1.9, uv[:, 1] * 1.1,
                               0.2 * torch.sin(3 * uv[:, 0]) * torch.cos(2 * uv[:, 1])], 1)
    s = 2.0 / math.sqrt(n)
    scene.scales = s * torch.exp(0.5 * torch.randn(n, 3, generator=g))
    scene.scales[:, 2] *= 0.2
    return scene


def _norm_err(a, b):
    return float((a - b).norm() / b.norm().clamp_min(1e-30))


@pytest.mark.parametrize("n,width,height", [(1_000_000, 1920, 1080), (200_000, 1280, 720)])
def test_large_scene_matches_cpu(n, width, height):
    """Launch and scratch sizes at production scale (tens of millions of tile pairs). Compared
    by norm: at this size some decisions fall within float rounding of a threshold."""
    scene = _surface_scene(n, width, height, seed=n % 97)
    cpu = run(scene, "cpu", torch.float32, beta=0.5)
    cuda = run(scene, "cuda", torch.float32, beta=0.5)
    errors = {name: _norm_err(cuda[name], cpu[name]) for name in cpu if name != "radii"}
    fwd = {k: v for k, v in errors.items() if not k.startswith(("grad_", "absgrad")) and v > 1e-4}
    grads = {k: v for k, v in errors.items() if k.startswith(("grad_", "absgrad")) and v > 2e-3}
    assert int((cuda["radii"] != cpu["radii"]).sum()) <= n // 100_000
    assert not fwd and not grads, f"norm-relative errors over tolerance: {fwd} {grads}"
