"""The rasterizer's result type."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

__all__ = ["RasterOutput"]


@dataclass
class RasterOutput:
    """What one disentangled rasterization pass returns.

    Image-shaped fields are (H, W, channels). `depth` is the geometry-alpha-weighted sum of
    camera z (divide by `alpha_g` for the expected depth). `absgrad_c` and `absgrad_g` are filled
    by backward: per Gaussian, the sum over pixels of |dL/d mean2d| from each branch (AbsGS).
    """

    color: Tensor       # (H, W, C) appearance features, plus (1 - alpha_c) * background
    geometry: Tensor    # (H, W, G) geometry features blended with the geometry alpha
    depth: Tensor       # (H, W, 1) sum of z * alpha_g * T_g
    alpha_c: Tensor     # (H, W, 1) appearance coverage, 1 - final transmittance
    alpha_g: Tensor     # (H, W, 1) geometry coverage
    radii: Tensor       # (N,) int32 screen radius in pixels, 0 where not drawn
    means2d: Tensor     # (N, 2) projected centres, retains grad when the inputs require it
    absgrad_c: Tensor   # (N, 2)
    absgrad_g: Tensor   # (N, 2)
    contribution: Tensor  # (N,) max over pixels of alpha * T in either branch (for pruning)
