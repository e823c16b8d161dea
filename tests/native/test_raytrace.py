"""The Gaussian ray tracer (ambient occlusion) against its dense reference and physical cases."""

from __future__ import annotations

import math

import pytest
import torch

from native import gaussian_visibility, trace_visibility
from native.reference import fibonacci_hemisphere
from scenes import random_scene

# The native tracer stops a ray once T < 1e-4 (the product is order-independent), so it can
# differ from the full product by at most 1e-4 per ray, hence per visibility value.
TOL = 1.5e-4


def _random_points(m: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    origins = (torch.rand(m, 3, generator=g) * 2 - 1) * 1.2
    normals = torch.randn(m, 3, generator=g)
    return origins, normals / normals.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_dense_reference(seed):
    s = random_scene(80, 8, 8, seed=seed, scale=(0.05, 0.3), opacity=(0.1, 1.0))
    origins, normals = _random_points(40, seed)
    exclude = torch.randint(-1, 80, (40,), generator=torch.Generator().manual_seed(seed))
    args = (origins, normals, s.means, s.quats, s.scales, s.opacity_g)
    nat = trace_visibility(*args, n_dirs=24, exclude=exclude)
    ref = trace_visibility(*[a.double() for a in args], n_dirs=24, exclude=exclude,
                           backend="reference")
    assert float((nat.double() - ref).abs().max()) < TOL
    assert 0.05 < float(nat.mean()) < 0.98, "the scene should occlude some rays and not all"


def test_gaussian_visibility_matches_reference_and_excludes_itself():
    s = random_scene(60, 8, 8, seed=4, scale=(0.05, 0.25))
    _, normals = _random_points(60, 4)
    nat = gaussian_visibility(s.means, s.quats, s.scales, s.opacity_g, normals, n_dirs=32)
    ref = gaussian_visibility(s.means.double(), s.quats.double(), s.scales.double(),
                              s.opacity_g.double(), normals.double(), n_dirs=32,
                              backend="reference")
    assert float((nat.double() - ref).abs().max()) < TOL
    # One opaque Gaussian alone: its own rays start at its centre but it does not occlude itself.
    alone = gaussian_visibility(s.means[:1], s.quats[:1], s.scales[:1], torch.ones(1),
                                normals[:1])
    assert float(alone[0]) == pytest.approx(1.0)


def _slab(z: float, size: float = 50.0, thickness: float = 0.01):
    """One huge, fully opaque, flat Gaussian: the plane z = `z`."""
    means = torch.tensor([[0.0, 0.0, z]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    scales = torch.tensor([[size, size, thickness]])
    return means, quats, scales, torch.ones(1)


def test_open_sky_and_covered_point():
    origin = torch.zeros(1, 3)
    up, down = torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    means, quats, scales, opacity = _slab(1.0)
    assert float(trace_visibility(origin, up, means[:0], quats[:0], scales[:0], opacity[:0])) == 1.0
    covered = float(trace_visibility(origin, up, means, quats, scales, opacity))
    facing_away = float(trace_visibility(origin, down, means, quats, scales, opacity))
    assert covered < 0.02, covered
    assert facing_away == pytest.approx(1.0, abs=1e-6)


def test_wall_blocks_about_half_of_a_tilted_hemisphere():
    # A vertical opaque wall x = 0.5 next to a point whose normal points at the wall: the
    # hemisphere is the half-space x > 0, and the wall hides (almost) all of it except grazing
    # directions; a normal along the wall (+z) sees half of its hemisphere blocked.
    means = torch.tensor([[0.5, 0.0, 0.0]])
    quats = torch.tensor([[math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0]])  # z -> x
    scales = torch.tensor([[100.0, 100.0, 0.01]])
    origin = torch.zeros(1, 3)
    toward = float(trace_visibility(origin, torch.tensor([[1.0, 0.0, 0.0]]), means, quats,
                                    scales, torch.ones(1), n_dirs=256))
    along = float(trace_visibility(origin, torch.tensor([[0.0, 0.0, 1.0]]), means, quats,
                                   scales, torch.ones(1), n_dirs=256))
    assert toward < 0.05
    assert along == pytest.approx(0.5, abs=0.05)


def test_fibonacci_hemisphere_is_uniform():
    d = fibonacci_hemisphere(512)
    assert torch.allclose(d.norm(dim=-1), torch.ones(512, dtype=torch.float64))
    assert bool((d[:, 2] > 0).all())
    assert float(d[:, 2].mean()) == pytest.approx(0.5, abs=1e-3)  # uniform on the hemisphere
    assert float(d[:, :2].mean(0).abs().max()) < 0.02


@pytest.mark.parametrize("change,name", [
    (lambda a: a.__setitem__(1, a[1] * 2), "normals"),
    (lambda a: a.__setitem__(0, a[0][:, :2]), "origins"),
    (lambda a: a.__setitem__(4, -a[4]), "scales"),
    (lambda a: a.__setitem__(5, a[5] + 2), "opacity"),
    (lambda a: a.__setitem__(3, a[3].double()), "quats"),
    (lambda a: a.__setitem__(2, a[2].index_fill(0, torch.tensor([0]), float("nan"))), "means"),
])
def test_bad_arguments_are_named(change, name):
    s = random_scene(5, 8, 8, seed=0)
    origins, normals = _random_points(3, 0)
    args = [origins, normals, s.means, s.quats, s.scales, s.opacity_g]
    change(args)
    with pytest.raises(ValueError, match=name):
        trace_visibility(*args)


def _flat_surface(n_side: int = 12, spacing: float = 0.1):
    """Overlapping thin discs tiling the plane z = 0 (about three deep), normals +z."""
    xs = torch.arange(n_side, dtype=torch.float32) * spacing
    gx, gy = torch.meshgrid(xs, xs, indexing="ij")
    n = gx.numel()
    means = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.zeros(n)], -1)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)
    scales = torch.tensor([[spacing, spacing, spacing * 0.05]]).repeat(n, 1)
    normals = torch.tensor([[0.0, 0.0, 1.0]]).repeat(n, 1)
    return means, quats, scales, torch.full((n,), 0.9), normals


def test_flat_surface_sees_its_sky():
    means, quats, scales, opacity, normals = _flat_surface()
    vis = gaussian_visibility(means, quats, scales, opacity, normals)
    # Nothing lies above a plane: every Gaussian sees (nearly) the whole hemisphere.
    assert float(vis.min()) > 0.95, float(vis.min())
    # Without the offset, rays start inside the overlapping neighbours and see almost nothing.
    stuck = trace_visibility(means, normals, means, quats, scales, opacity,
                             exclude=torch.arange(means.shape[0]))
    assert float(stuck.mean()) < 0.5
    # A lid over the plane darkens it.
    lid_m, lid_q, lid_s, lid_o = _slab(0.3)
    all_m = torch.cat([means, lid_m]); all_q = torch.cat([quats, lid_q])
    all_s = torch.cat([scales, lid_s]); all_o = torch.cat([opacity, lid_o])
    covered = gaussian_visibility(all_m, all_q, all_s, all_o,
                                  torch.cat([normals, torch.tensor([[0.0, 0.0, 1.0]])]))
    assert float(covered[:-1].max()) < 0.05
