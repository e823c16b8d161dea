"""The CUDA ray tracer against the CPU one (the same BVH and walk, raytrace_bvh.h) on one GPU.

Skipped without a CUDA device or when the extension was built without CUDA. Every scene is
seeded. The CPU op is the reference here: both trace the same host-built tree, so they differ
only by rounding (nvcc's FMA contraction, the device's cos/sin/exp). In float64 that stays far
below 1e-10. In float32 nearly every origin agrees to about 1e-5, but a ray whose rounding flips
a decision (a box test at a box's edge, the 1/255 alpha cut, the T < 1e-4 stop) moves its
origin's visibility by up to one ray's weight (2 / n_dirs at most) times the alpha at stake
(at most about 0.011 at a 3-sigma box edge): `_assert_close` allows that for a few origins.
Where float32 itself is ill-conditioned (a razor-thin slab, tiny Gaussians far along a ray),
the CPU float32 op is no closer to float64 than that, so CUDA float32 is judged against float64.
"""

from __future__ import annotations

import math

import pytest
import torch

from native import gaussian_visibility, trace_visibility

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]

F32_TOL = 1e-4   # abs visibility difference of all but F32_FLIPS of the origins, float32
F32_FLIPS = 0.01  # share of float32 origins that may differ by one flipped ray
F64_TOL = 1e-10  # max abs visibility difference, float64


@pytest.fixture(scope="module", autouse=True)
def _cuda_build():
    from native._backend import load

    if not getattr(load(), "has_cuda", lambda: False)():
        pytest.skip("the native extension was built without CUDA")


def _gaussians(n: int, seed: int, scale=(0.05, 0.3), opacity=(0.1, 1.0), spread=1.0):
    """N Gaussians in a cube of half-size `spread` (the distribution of scenes.random_scene)."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) * 2 - 1) * spread
    quats = torch.randn(n, 4, generator=g)
    lo, hi = math.log(scale[0]), math.log(scale[1])
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=g))
    op = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g)
    return means, quats, scales, op


def _points(m: int, seed: int, spread=1.2):
    g = torch.Generator().manual_seed(seed + 1000)
    origins = (torch.rand(m, 3, generator=g) * 2 - 1) * spread
    normals = torch.randn(m, 3, generator=g)
    return origins, normals / normals.norm(dim=-1, keepdim=True)


def _assert_close(cpu, gpu, n_dirs: int):
    diff = (cpu.double() - gpu.double()).abs()
    if cpu.dtype == torch.float64:
        assert float(diff.max()) < F64_TOL
        return
    assert float((diff > F32_TOL).double().mean()) <= F32_FLIPS, diff.max()
    assert float(diff.max()) < 0.012 * 2 / n_dirs  # one ray at most, at a box edge


def _both(args, dtype, **kw):
    """(CPU result, CUDA result moved to the CPU) of trace_visibility on `args` in `dtype`."""
    cast = [a.to(dtype) if a.is_floating_point() else a for a in args]
    exclude = kw.pop("exclude", None)
    cpu = trace_visibility(*cast, exclude=exclude, **kw)
    gpu_args = [a.cuda() for a in cast]
    gpu = trace_visibility(*gpu_args, exclude=None if exclude is None else exclude.cuda(), **kw)
    assert gpu.device.type == "cuda" and gpu.dtype == dtype and gpu.shape == cpu.shape
    return cpu, gpu.cpu()


DTYPES = [torch.float32, torch.float64]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_cpu_on_random_scenes(seed, dtype):
    n, m = 400, 3000
    means, quats, scales, op = _gaussians(n, seed)
    origins, normals = _points(m, seed)
    exclude = torch.randint(-1, n, (m,), generator=torch.Generator().manual_seed(seed))
    cpu, gpu = _both((origins, normals, means, quats, scales, op), dtype, n_dirs=32,
                     exclude=exclude)
    _assert_close(cpu, gpu, 32)
    assert 0.1 < float(cpu.mean()) < 0.95, "the scene should occlude some rays and not all"


@pytest.mark.parametrize("dtype", DTYPES)
def test_gaussian_visibility_matches_cpu(dtype):
    means, quats, scales, op = (t.to(dtype) for t in _gaussians(2000, 7, scale=(0.02, 0.1)))
    _, normals = _points(2000, 7)
    normals = normals.to(dtype)
    cpu = gaussian_visibility(means, quats, scales, op, normals, n_dirs=24)
    gpu = gaussian_visibility(means.cuda(), quats.cuda(), scales.cuda(), op.cuda(),
                              normals.cuda(), n_dirs=24)
    assert gpu.device.type == "cuda"
    _assert_close(cpu, gpu.cpu(), 24)


def test_exclude_is_honoured():
    # One opaque slab over the origin: it hides the sky unless the origin excludes it.
    means = torch.tensor([[0.0, 0.0, 1.0]], device="cuda")
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], device="cuda")
    scales = torch.tensor([[50.0, 50.0, 0.01]], device="cuda")
    opacity = torch.ones(1, device="cuda")
    origins = torch.zeros(2, 3, device="cuda")
    normals = torch.tensor([[0.0, 0.0, 1.0]], device="cuda").repeat(2, 1)
    exclude = torch.tensor([-1, 0], device="cuda")
    vis = trace_visibility(origins, normals, means, quats, scales, opacity, exclude=exclude)
    assert float(vis[0]) < 0.02
    assert float(vis[1]) == 1.0


def test_random_exclude_changes_results_like_the_cpu():
    means, quats, scales, op = _gaussians(300, 3, scale=(0.1, 0.4))
    origins = means[:200].clone()  # origins at Gaussian centres: excluding matters
    _, normals = _points(origins.shape[0], 3)
    own = torch.arange(origins.shape[0])
    args = (origins, normals, means, quats, scales, op)
    cpu_own, gpu_own = _both(args, torch.float64, n_dirs=16, exclude=own)
    cpu_none, gpu_none = _both(args, torch.float64, n_dirs=16)
    _assert_close(cpu_own, gpu_own, 16)
    _assert_close(cpu_none, gpu_none, 16)
    # Dropping a factor only raises T (up to where either ray stops below T = 1e-4).
    assert bool((gpu_own >= gpu_none - 1e-4).all()) and float((gpu_own - gpu_none).max()) > 0.1


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_empty_inputs(dtype):
    means, quats, scales, op = (t.to(dtype).cuda() for t in _gaussians(10, 0))
    origins, normals = (t.to(dtype).cuda() for t in _points(5, 0))
    no_gaussians = trace_visibility(origins, normals, means[:0], quats[:0], scales[:0], op[:0])
    assert no_gaussians.device.type == "cuda" and no_gaussians.dtype == dtype
    assert torch.equal(no_gaussians.cpu(), torch.ones(5, dtype=dtype))
    no_origins = trace_visibility(origins[:0], normals[:0], means, quats, scales, op)
    assert no_origins.device.type == "cuda" and no_origins.shape == (0,)
    both = trace_visibility(origins[:0], normals[:0], means[:0], quats[:0], scales[:0], op[:0])
    assert both.shape == (0,)


def _huge(thickness: float):
    """One Gaussian far larger than the scene (every origin lies in its box), tilted."""
    return (torch.tensor([[0.0, 0.0, 0.5]]), torch.tensor([[0.9, 0.1, 0.3, 0.2]]),
            torch.tensor([[80.0, 60.0, thickness]]), torch.tensor([0.7]))


@pytest.mark.parametrize("dtype", DTYPES)
def test_one_huge_gaussian(dtype):
    # Alone (the tree is one leaf), then mixed into a scene where its box overlaps every other.
    big = _huge(2.0)
    origins, normals = _points(1000, 5)
    cpu, gpu = _both((origins, normals, *big), dtype, n_dirs=64)
    _assert_close(cpu, gpu, 64)
    assert float(gpu.min()) < 0.35 and float(gpu.max()) > 0.5
    small = _gaussians(200, 5, scale=(0.02, 0.2))
    mixed = [torch.cat([a, b]) for a, b in zip(big, small)]
    cpu, gpu = _both((origins, normals, *mixed), dtype, n_dirs=32)
    _assert_close(cpu, gpu, 32)


def test_huge_thin_slab():
    # Scales 4000 to 1: q = c - 2 t b + t^2 a cancels badly in float32, so the float32 CPU op is
    # itself about 6e-3 off the float64 one; CUDA float32 must be as close, float64 exact.
    slab = _huge(0.02)
    origins, normals = _points(1000, 5)
    args = (origins, normals, *slab)
    cpu64, gpu64 = _both(args, torch.float64, n_dirs=64)
    _assert_close(cpu64, gpu64, 64)
    cpu32, gpu32 = _both(args, torch.float32, n_dirs=64)
    assert float((cpu32.double() - cpu64).abs().max()) < 1e-2
    assert float((gpu32.double() - cpu64).abs().max()) < 1e-2


def test_many_gaussians_and_origins():
    # Launch sizes: 391 blocks of origins over a tree of ~100k nodes, rays crossing many small
    # Gaussians. Origins are independent, so the CPU checks an evenly spaced subset. Rays that
    # pass near tiny Gaussians far away evaluate alpha with heavy cancellation, so here float32
    # is judged against float64 (the CPU float32 op strays about as far, ~1% of origins > 1e-4).
    n, m, n_dirs = 200_000, 50_000, 16
    scene = _gaussians(n, 11, scale=(0.002, 0.02))
    origins, normals = _points(m, 11)
    exclude = torch.randint(-1, n, (m,), generator=torch.Generator().manual_seed(11))
    pick = torch.arange(0, m, 16)
    args = (origins, normals, *scene)
    gpu = {}
    for dtype in DTYPES:
        a = [t.to(dtype).cuda() for t in args]
        v = trace_visibility(*a, n_dirs=n_dirs, exclude=exclude.cuda())
        assert v.shape == (m,) and v.dtype == dtype and bool(torch.isfinite(v).all())
        assert bool(((v >= 0) & (v <= 1)).all())
        gpu[dtype] = v.cpu()[pick].double()
    assert 0.05 < float(gpu[torch.float64].mean()) < 0.95
    sub = [t[pick] for t in (origins, normals)] + list(scene)
    cpu64 = trace_visibility(*[t.double() for t in sub], n_dirs=n_dirs, exclude=exclude[pick])
    cpu32 = trace_visibility(*sub, n_dirs=n_dirs, exclude=exclude[pick]).double()
    assert float((gpu[torch.float64] - cpu64).abs().max()) < F64_TOL
    err_gpu, err_cpu = (gpu[torch.float32] - cpu64).abs(), (cpu32 - cpu64).abs()
    assert float(err_gpu.mean()) <= 1.5 * float(err_cpu.mean()) + 1e-7
    assert float(err_gpu.max()) <= 2 * float(err_cpu.max()) + 1e-5


def test_tensors_on_two_devices_are_named():
    means, quats, scales, op = _gaussians(5, 0)
    origins, normals = _points(3, 0)
    with pytest.raises(ValueError, match="means"):
        trace_visibility(origins.cuda(), normals.cuda(), means, quats.cuda(), scales.cuda(),
                         op.cuda())
    with pytest.raises(ValueError, match="exclude"):
        trace_visibility(origins.cuda(), normals.cuda(), means.cuda(), quats.cuda(),
                         scales.cuda(), op.cuda(), exclude=torch.full((3,), -1))


def test_reference_backend_runs_on_cuda():
    means, quats, scales, op = _gaussians(50, 4)
    origins, normals = _points(20, 4)
    args = [t.double() for t in (origins, normals, means, quats, scales, op)]
    ref = trace_visibility(*[a.cuda() for a in args], n_dirs=16, backend="reference")
    nat = trace_visibility(*[a.cuda() for a in args], n_dirs=16)
    assert ref.device.type == "cuda"
    assert float((ref - nat).abs().max()) < 1.5e-4  # the native early stop at T < 1e-4
