"""Autograd functions over the native ops: one per differentiable op (projection, rasterization)."""

from __future__ import annotations

import torch
from torch import Tensor

from native._backend import load

__all__ = ["Projection", "Rasterization", "intersect_tiles", "TILE_SIZE"]

TILE_SIZE = 16


def _grad_or_zeros(g: Tensor | None, like: Tensor) -> Tensor:
    return torch.zeros_like(like) if g is None else g.contiguous()


class Projection(torch.autograd.Function):
    """(means, quats, scales, opacity_c, opacity_g, viewmat, K) -> means2d, conics, depths,
    mixed opacities (N,2), rects (N,4) int32, radii (N,) int32."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacity_c, opacity_g, viewmat, K, width, height, beta,
                eps2d, antialiased, near, far):
        out = load().projection_fwd(means, quats, scales, opacity_c, opacity_g, viewmat, K,
                                    width, height, beta, eps2d, antialiased, near, far)
        ctx.save_for_backward(means, quats, scales, opacity_c, opacity_g, viewmat, K)
        ctx.config = (width, height, beta, eps2d, antialiased, near, far)
        ctx.mark_non_differentiable(out[4], out[5])
        return out

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, v_opac, _rects, _radii):
        means, quats, scales, opacity_c, opacity_g, viewmat, K = ctx.saved_tensors
        width, height, beta, eps2d, antialiased, near, far = ctx.config
        n = means.shape[0]
        grads = load().projection_bwd(
            means, quats, scales, opacity_c, opacity_g, viewmat, K, width, height, beta, eps2d,
            antialiased, near, far,
            _grad_or_zeros(v_means2d, means.new_empty(n, 2)),
            _grad_or_zeros(v_conics, means.new_empty(n, 3)),
            _grad_or_zeros(v_depths, means.new_empty(n)),
            _grad_or_zeros(v_opac, means.new_empty(n, 2)),
        )
        return (*grads, None, None, None, None, None, None, None)


def intersect_tiles(rects: Tensor, depths: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
    """Tile offsets (n_tiles+1,) int64 and Gaussian ids (M,) int32 sorted by depth per tile."""
    return load().intersect_tiles(rects, depths.detach(), width, height, TILE_SIZE)


class Rasterization(torch.autograd.Function):
    """Both branches blended in one pass. Returns color, geometry, depth, alpha_c, alpha_g and the
    per-Gaussian contribution (max alpha*T, not differentiable). The backward pass adds the
    per-branch AbsGS sums into `absgrad` (N,4) in place."""

    @staticmethod
    def forward(ctx, means2d, conics, opac, depths, colors, geometry, rects, offsets, ids, width,
                height, absgrad, geometry_branch):
        color, geo, depth, trans, stops, contrib = load().rasterize_fwd(
            means2d, conics, opac, depths, colors, geometry, rects, offsets, ids, width, height,
            TILE_SIZE, geometry_branch)
        ctx.save_for_backward(means2d, conics, opac, depths, colors, geometry, rects, offsets, ids,
                              color, geo, depth, trans, stops)
        ctx.config = (width, height, geometry_branch)
        ctx.absgrad = absgrad
        alpha = 1.0 - trans
        ctx.mark_non_differentiable(contrib)
        return color, geo, depth, alpha[..., 0:1], alpha[..., 1:2], contrib

    @staticmethod
    def backward(ctx, v_color, v_geo, v_depth, v_alpha_c, v_alpha_g, _contrib):
        (means2d, conics, opac, depths, colors, geometry, rects, offsets, ids, color, geo, depth,
         trans, stops) = ctx.saved_tensors
        width, height, geometry_branch = ctx.config
        v_alpha = torch.cat([_grad_or_zeros(v_alpha_c, depth), _grad_or_zeros(v_alpha_g, depth)],
                            dim=-1)
        g_m2, g_cn, g_op, g_z, g_col, g_geo, g_abs = load().rasterize_bwd(
            means2d, conics, opac, depths, colors, geometry, rects, offsets, ids, width, height,
            TILE_SIZE, geometry_branch, color, geo, depth, trans, stops,
            _grad_or_zeros(v_color, color), _grad_or_zeros(v_geo, geo),
            _grad_or_zeros(v_depth, depth), v_alpha.contiguous())
        with torch.no_grad():
            ctx.absgrad.add_(g_abs)
        return g_m2, g_cn, g_op, g_z, g_col, g_geo, None, None, None, None, None, None, None
