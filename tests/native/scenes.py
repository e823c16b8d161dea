"""Random scenes for rasterizer tests and benchmarks."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["Scene", "random_scene", "look_at"]


@dataclass
class Scene:
    means: Tensor
    quats: Tensor
    scales: Tensor
    opacity_c: Tensor
    opacity_g: Tensor
    colors: Tensor
    geometry: Tensor
    viewmat: Tensor
    K: Tensor
    width: int
    height: int

    def args(self) -> tuple:
        return (self.means, self.quats, self.scales, self.opacity_c, self.opacity_g, self.colors,
                self.geometry, self.viewmat, self.K, self.width, self.height)

    def float_tensors(self) -> dict[str, Tensor]:
        return {k: v for k, v in vars(self).items() if isinstance(v, Tensor)}

    def to(self, dtype: torch.dtype) -> "Scene":
        kw = {k: (v.detach().to(dtype).clone() if isinstance(v, Tensor) else v)
              for k, v in vars(self).items()}
        return Scene(**kw)

    def requires_grad_(self) -> "Scene":
        for t in self.float_tensors().values():
            t.requires_grad_(True)
        return self


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> Tensor:
    """World-to-camera (4,4), OpenCV axes (x right, y down, z forward)."""
    from core.synth.generate import look_at as look_at_np

    return torch.tensor(look_at_np(eye, target, up), dtype=torch.float32)


def random_scene(n: int, width: int, height: int, *, C: int = 3, G: int = 5, seed: int = 0,
                 scale: tuple[float, float] = (0.02, 0.15), opacity: tuple[float, float] = (0.05, 1.0),
                 spread: float = 1.0, behind: float = 0.0, offscreen: float = 0.0,
                 fov_deg: float = 50.0) -> Scene:
    """N Gaussians in a cube of half-size `spread` around the origin, seen from distance 3.

    `behind` and `offscreen` are fractions of Gaussians moved behind the camera or far to the
    side of the view frustum.
    """
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) * 2 - 1) * spread
    nb, no = int(n * behind), int(n * offscreen)
    if nb:
        means[:nb, 2] = -3.0 - torch.rand(nb, generator=g) * 2  # camera at z=-3 looks to +z
    if no:
        means[nb:nb + no, 0] = 8.0 + torch.rand(no, generator=g) * 4
    quats = torch.randn(n, 4, generator=g)
    lo, hi = math.log(scale[0]), math.log(scale[1])
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=g))
    opacity_c = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g)
    opacity_g = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g)
    colors = torch.rand(n, C, generator=g)
    geometry = torch.randn(n, G, generator=g)
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0.0, width / 2 + 0.3], [0.0, f * 1.02, height / 2 - 0.2], [0, 0, 1]])
    viewmat = look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0))
    return Scene(means, quats, scales, opacity_c, opacity_g, colors, geometry, viewmat, K,
                 width, height)
