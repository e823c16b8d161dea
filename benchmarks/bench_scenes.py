"""Benchmark scenes: what a trained model looks like to the rasterizer.

`surface_scene`: flat Gaussians (one short axis along the surface normal) covering a bumpy closed
surface about three layers deep, like a reconstructed performer, plus 5% floaters in the volume.
`volume_scene`: the random cube of the tests, every Gaussian in open space (a harder case).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "native"))
from scenes import Scene, look_at, random_scene  # noqa: E402

__all__ = ["surface_scene", "volume_scene", "Scene"]


def _quat_from_z(normal: torch.Tensor, twist: torch.Tensor) -> torch.Tensor:
    """Quaternions (w,x,y,z) turning +z onto `normal`, then twisting about it."""
    z = torch.tensor([0.0, 0.0, 1.0]).expand_as(normal)
    axis = torch.linalg.cross(z, normal)
    s = axis.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    angle = torch.atan2(s[:, 0], (z * normal).sum(-1))
    q_align = torch.cat([torch.cos(angle / 2)[:, None], axis / s * torch.sin(angle / 2)[:, None]], -1)
    q_twist = torch.stack([torch.cos(twist / 2), 0 * twist, 0 * twist, torch.sin(twist / 2)], -1)
    w1, x1, y1, z1 = q_align.unbind(-1)
    w2, x2, y2, z2 = q_twist.unbind(-1)
    return torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)


def surface_scene(n: int, width: int, height: int, *, C: int = 3, G: int = 5, seed: int = 0,
                  layers: float = 3.0, fov_deg: float = 45.0) -> Scene:
    g = torch.Generator().manual_seed(seed)
    n_float = n // 20
    n_surf = n - n_float
    d = torch.randn(n_surf, 3, generator=g)
    d = d / d.norm(dim=-1, keepdim=True)
    # A bumpy blob: radius varies smoothly with direction.
    r = 1.0 + 0.15 * torch.sin(3 * d[:, 0]) * torch.cos(2 * d[:, 1]) + 0.1 * torch.sin(5 * d[:, 2])
    pts = d * r[:, None] * torch.tensor([0.7, 1.0, 0.7])
    area = 4 * math.pi * 0.8 ** 2
    disc = math.sqrt(layers * area / (math.pi * n_surf))  # disc radius for `layers` coverage
    s_tan = disc * torch.exp(0.3 * torch.randn(n_surf, 2, generator=g))
    s_norm = disc * 0.05 * torch.ones(n_surf, 1)
    scales = torch.cat([s_tan, s_norm], -1)
    quats = _quat_from_z(d, torch.rand(n_surf, generator=g) * 2 * math.pi)
    fl = random_scene(n_float, width, height, C=C, G=G, seed=seed + 1, spread=1.2,
                      scale=(disc * 0.5, disc * 2))
    means = torch.cat([pts, fl.means])
    quats = torch.cat([quats, fl.quats])
    scales = torch.cat([scales, fl.scales])
    opacity_c = torch.cat([0.3 + 0.7 * torch.rand(n_surf, generator=g), fl.opacity_c * 0.3])
    opacity_g = torch.cat([0.3 + 0.7 * torch.rand(n_surf, generator=g), fl.opacity_g * 0.3])
    colors = torch.rand(n, C, generator=g)
    geometry = torch.randn(n, G, generator=g)
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    viewmat = look_at((0.0, -0.5, -3.2), (0.0, 0.0, 0.0))
    return Scene(means.contiguous(), quats.contiguous(), scales.contiguous(), opacity_c,
                 opacity_g, colors, geometry, viewmat, K, width, height)


def volume_scene(n: int, width: int, height: int, *, C: int = 3, G: int = 5, seed: int = 0) -> Scene:
    return random_scene(n, width, height, C=C, G=G, seed=seed, scale=(0.004, 0.03))
