"""The public rasterizer: checks its inputs, then projection -> tile binning -> blending."""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from native._backend import has_cuda
from native._validate import check_inputs
from native._wrapper import Projection, Rasterization, intersect_tiles
from native.reference import rasterize as reference
from native.types import RasterOutput

__all__ = ["rasterize", "Backend"]

Backend = Literal["native", "reference"]


def rasterize(
    means: Tensor,       # (N, 3) world-space centres
    quats: Tensor,       # (N, 4) rotations (w, x, y, z), not necessarily normalized
    scales: Tensor,      # (N, 3) positive standard deviations
    opacity_c: Tensor,   # (N,) appearance opacity in [0, 1]
    opacity_g: Tensor,   # (N,) geometry opacity in [0, 1]
    colors: Tensor,      # (N, C) features blended with the appearance alpha
    geometry: Tensor | None,  # (N, G) features blended with the geometry alpha; None: no branch
    viewmat: Tensor,     # (4, 4) world-to-camera, OpenCV axes
    K: Tensor,           # (3, 3) intrinsics
    width: int,
    height: int,
    *,
    beta: float = 0.0,
    eps2d: float = 0.3,
    antialiased: bool = False,
    near: float = 0.01,
    far: float = 1e10,
    background: Tensor | None = None,  # (C,)
    backend: Backend = "native",
    validate: bool = True,
) -> RasterOutput:
    """Render both branches of N Gaussians in one pass (docs/design.md section 3.4).

    With `geometry=None` only the appearance branch runs (a plain single-opacity RGB pass, as in
    the first training stage): `geometry` comes back (H, W, 0) and `depth` and `alpha_g` are zero.

    `backend="reference"` runs the dense plain-PyTorch implementation (`native.reference`), which
    needs O(N * H * W) memory but works on any device. Every output is differentiable with
    respect to every float input. Shapes, dtypes and devices are checked on every call;
    `validate=False` skips the checks of the values (finite, positive scales, opacities in
    [0, 1]), which read every element: a training loop checks them once per run.
    """
    if backend == "reference":
        return reference(means, quats, scales, opacity_c, opacity_g, colors, geometry, viewmat,
                         K, width, height, beta=beta, eps2d=eps2d, antialiased=antialiased,
                         near=near, far=far, background=background, validate=validate)
    if backend != "native":
        raise ValueError(f"backend must be 'native' or 'reference', got {backend!r}")
    check_inputs(means, quats, scales, opacity_c, opacity_g, colors, geometry, viewmat, K,
                 width, height, beta, eps2d, near, far, background, require_contiguous=True,
                 values=validate)
    if means.device.type != "cpu":
        if means.device.type != "cuda" or not has_cuda():
            raise ValueError(
                f"means is on {means.device}, but the native extension was built without CUDA "
                "(it needs a CUDA build of torch and nvcc); pass backend='reference' or move "
                "the tensors to the CPU")

    width, height = int(width), int(height)
    geometry_branch = geometry is not None
    if geometry is None:
        geometry = means.new_zeros(means.shape[0], 0)
    means2d, conics, depths, opac, rects, radii = Projection.apply(
        means, quats, scales, opacity_c, opacity_g, viewmat, K, width, height, float(beta),
        float(eps2d), bool(antialiased), float(near), float(far))
    if means2d.requires_grad:
        means2d.retain_grad()
    offsets, ids = intersect_tiles(rects, depths, width, height)
    absgrad = torch.zeros(means.shape[0], 4, dtype=means.dtype, device=means.device)
    color, geo, depth, alpha_c, alpha_g, contribution = Rasterization.apply(
        means2d, conics, opac, depths, colors, geometry, rects, offsets, ids, width, height,
        absgrad, geometry_branch)
    if background is not None:
        color = color + (1.0 - alpha_c) * background
    return RasterOutput(color=color, geometry=geo, depth=depth, alpha_c=alpha_c, alpha_g=alpha_g,
                        radii=radii, means2d=means2d, absgrad_c=absgrad[:, 0:2],
                        absgrad_g=absgrad[:, 2:4], contribution=contribution)
