"""Plain PyTorch reference of `native.rasterize`: the same signature and result, computed densely
(every Gaussian at every pixel) with autograd, on any device and dtype.

It states the math of docs/design.md section 3.4 as directly as possible; tests compare the native
op against it. Memory is O(N * H * W), so it is for small scenes (or as a slow fallback).
"""

from __future__ import annotations

import torch
from torch import Tensor

from native._validate import check_inputs
from native.types import RasterOutput

__all__ = ["rasterize", "quat_to_rotmat", "trace_visibility", "fibonacci_hemisphere"]

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
FOV_GUARD = 0.15


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """(N, 4) quaternions (w, x, y, z), any norm -> (N, 3, 3) rotation matrices."""
    w, x, y, z = (quats / quats.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def _project(means, quats, scales, viewmat, K, width, height, eps2d, antialiased, near, far):
    """Camera-space means, 2D means, blurred 2D covariances (N,2,2), compensation, validity."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    valid = (z > near) & (z < far)
    zs = torch.where(valid, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    gx, gy = FOV_GUARD * width, FOV_GUARD * height
    tx = zs * torch.minimum(torch.maximum(x / zs, -(cx + gx) / fx), (width - cx + gx) / fx)
    ty = zs * torch.minimum(torch.maximum(y / zs, -(cy + gy) / fy), (height - cy + gy) / fy)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / zs**2,
                     zero, fy / zs, -fy * ty / zs**2], dim=-1).reshape(-1, 2, 3)
    M = quat_to_rotmat(quats) * scales[:, None, :]
    cov_cam = R @ (M @ M.transpose(1, 2)) @ R.T
    cov2d = J @ cov_cam @ J.transpose(1, 2)
    det_orig = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
    cov2d = cov2d + eps2d * torch.eye(2, dtype=means.dtype, device=means.device)
    det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
    valid = valid & (det > 0)
    if antialiased:
        ratio = det_orig / torch.where(valid, det, torch.ones_like(det))
        pos = ratio > 0
        comp = torch.where(pos, torch.sqrt(torch.where(pos, ratio, torch.ones_like(ratio))), zero)
    else:
        comp = torch.ones_like(zs)
    mean2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)
    return p, mean2d, cov2d, comp, valid


def _radii(mean2d, cov2d, o_max, width, height) -> Tensor:
    """Screen radius as the native projection computes it (0 where nothing can be drawn)."""
    with torch.no_grad():
        k = 2 * torch.log(torch.clamp(o_max, min=1e-30) / ALPHA_MIN)
        kk = k * 1.001 + 1e-3
        ex = torch.sqrt(torch.clamp(kk * cov2d[:, 0, 0], min=0)) * 1.001 + 1e-2
        ey = torch.sqrt(torch.clamp(kk * cov2d[:, 1, 1], min=0)) * 1.001 + 1e-2
        u0, u1 = torch.ceil(mean2d[:, 0] - ex - 0.5), torch.floor(mean2d[:, 0] + ex - 0.5)
        v0, v1 = torch.ceil(mean2d[:, 1] - ey - 0.5), torch.floor(mean2d[:, 1] + ey - 0.5)
        on = ((o_max >= ALPHA_MIN) & (u1 >= 0) & (v1 >= 0) & (u0 <= width - 1)
              & (v0 <= height - 1) & (torch.maximum(u0, torch.zeros_like(u0))
                                      <= torch.minimum(u1, torch.full_like(u1, width - 1)))
              & (torch.maximum(v0, torch.zeros_like(v0))
                 <= torch.minimum(v1, torch.full_like(v1, height - 1))))
        r = torch.clamp(torch.ceil(torch.maximum(ex, ey)), min=1)
        return torch.where(on, r, torch.zeros_like(r)).to(torch.int32)


def _composite(alpha: Tensor) -> tuple[Tensor, Tensor]:
    """Front-to-back weights (n, P) and final transmittance (P,) for alphas sorted by depth.

    A branch stops at the first Gaussian that would take T below T_MIN, without adding it; the
    running product before that point equals the plain cumulative product, so the stop mask can
    be read off it.
    """
    alpha = torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha))
    include = (torch.cumprod(1 - alpha, dim=0) >= T_MIN).detach()
    alpha = alpha * include
    trans = torch.cumprod(1 - alpha, dim=0)
    before = torch.cat([torch.ones_like(trans[:1]), trans[:-1]], dim=0)
    return alpha * before, trans[-1] if trans.shape[0] else torch.ones_like(alpha[0])


def _absgrad_hook(buffer: Tensor, index: Tensor):
    def hook(grad: Tensor) -> None:
        with torch.no_grad():
            buffer.index_add_(0, index, grad.abs().sum(dim=1))
    return hook


def rasterize(means, quats, scales, opacity_c, opacity_g, colors, geometry, viewmat, K, width,
              height, *, beta: float = 0.0, eps2d: float = 0.3, antialiased: bool = False,
              near: float = 0.01, far: float = 1e10, background: Tensor | None = None,
              validate: bool = True) -> RasterOutput:
    """Dense reference of `native.rasterize` (same arguments, same result)."""
    check_inputs(means, quats, scales, opacity_c, opacity_g, colors, geometry, viewmat, K,
                 width, height, beta, eps2d, near, far, background, require_contiguous=False,
                 values=validate)
    width, height = int(width), int(height)
    geometry_branch = geometry is not None
    if geometry is None:
        geometry = means.new_zeros(means.shape[0], 0)
    n, C, G = means.shape[0], colors.shape[1], geometry.shape[1]
    dtype, device = means.dtype, means.device
    p, mean2d, cov2d, comp, valid = _project(means, quats, scales, viewmat, K, width, height,
                                             eps2d, antialiased, near, far)
    o_c = 0.5 * comp * ((1 + beta) * opacity_c + (1 - beta) * opacity_g)
    o_g = 0.5 * comp * ((1 - beta) * opacity_c + (1 + beta) * opacity_g)
    mean2d = torch.where(valid[:, None], mean2d, torch.zeros_like(mean2d))
    if mean2d.requires_grad:
        mean2d.retain_grad()
    radii = torch.where(valid, _radii(mean2d, cov2d, torch.maximum(o_c, o_g), width, height),
                        torch.zeros(n, dtype=torch.int32, device=device))

    idx = torch.nonzero(valid).squeeze(1)
    idx = idx[torch.sort(p[idx, 2], stable=True).indices]
    P = width * height
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype, device=device),
                          torch.arange(width, dtype=dtype, device=device), indexing="ij")
    pix = torch.stack([u.reshape(-1) + 0.5, v.reshape(-1) + 0.5], dim=-1)  # (P, 2)
    cov = cov2d[idx]
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0]
    ca, cb, cc = cov[:, 1, 1] / det, -cov[:, 0, 1] / det, cov[:, 0, 0] / det
    absgrad = torch.zeros(n, 4, dtype=dtype, device=device)

    def branch_alpha(opacity: Tensor, hook_cols: slice) -> Tensor:
        # Each branch gets its own per-pixel copy of the means so that a hook can read the
        # per-pixel gradient from that branch alone (the AbsGS statistic).
        m = mean2d[idx][:, None, :].repeat(1, P, 1)
        if m.requires_grad:
            m.register_hook(_absgrad_hook(absgrad[:, hook_cols], idx))
        d = pix[None] - m
        dx, dy = d[..., 0], d[..., 1]
        e = -0.5 * (ca[:, None] * dx * dx + cc[:, None] * dy * dy) - cb[:, None] * dx * dy
        return torch.clamp(opacity[idx][:, None] * torch.exp(e), max=ALPHA_MAX)

    w_c, trans_c = _composite(branch_alpha(o_c, slice(0, 2)))
    if geometry_branch:
        w_g, trans_g = _composite(branch_alpha(o_g, slice(2, 4)))
    else:
        w_g, trans_g = torch.zeros_like(w_c), torch.ones_like(trans_c)
    color = (w_c.T @ colors[idx]).reshape(height, width, C)
    geo = (w_g.T @ geometry[idx]).reshape(height, width, G)
    depth = (w_g.T @ p[idx, 2:3]).reshape(height, width, 1)
    alpha_c = (1 - trans_c).reshape(height, width, 1)
    alpha_g = (1 - trans_g).reshape(height, width, 1)
    if background is not None:
        color = color + (1 - alpha_c) * background
    contribution = torch.zeros(n, dtype=dtype, device=device)
    if idx.numel() and P:
        contribution[idx] = torch.maximum(w_c.max(dim=1).values, w_g.max(dim=1).values).detach()
    return RasterOutput(color=color, geometry=geo, depth=depth, alpha_c=alpha_c, alpha_g=alpha_g,
                        radii=radii, means2d=mean2d, absgrad_c=absgrad[:, 0:2],
                        absgrad_g=absgrad[:, 2:4], contribution=contribution)



def fibonacci_hemisphere(n: int, dtype=torch.float64, device=None) -> Tensor:
    """(n, 3) directions on the hemisphere z >= 0 (see raytrace_math.h)."""
    i = torch.arange(n, dtype=torch.float64, device=device)
    z = 1 - (i + 0.5) / n
    r = torch.sqrt(torch.clamp(1 - z * z, min=0))
    phi = 2.39996322972865332 * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1).to(dtype)


def _normal_frame(n: Tensor) -> tuple[Tensor, Tensor]:
    x = torch.tensor([1.0, 0.0, 0.0], dtype=n.dtype, device=n.device).expand_as(n)
    y = torch.tensor([0.0, 1.0, 0.0], dtype=n.dtype, device=n.device).expand_as(n)
    a = torch.where((n[:, :1].abs() < 0.9), x, y)
    t = torch.linalg.cross(n, a)
    t = t / t.norm(dim=-1, keepdim=True)
    return t, torch.linalg.cross(n, t)


def trace_visibility(origins, normals, means, quats, scales, opacity, *, n_dirs: int = 64,
                     exclude: Tensor | None = None) -> Tensor:
    """Dense reference of `native.raytrace.trace_visibility`: every ray against every Gaussian.

    The native tracer stops a ray once T < 1e-4, so the two agree to about 1e-4 in visibility.
    """
    M, N = origins.shape[0], means.shape[0]
    if exclude is None:
        exclude = torch.full((M,), -1, dtype=torch.int64, device=origins.device)
    t, b = _normal_frame(normals)
    local = fibonacci_hemisphere(n_dirs, origins.dtype, origins.device)  # (D, 3)
    dirs = (local[None, :, 0:1] * t[:, None] + local[None, :, 1:2] * b[:, None]
            + local[None, :, 2:3] * normals[:, None])  # (M, D, 3)
    R = quat_to_rotmat(quats)
    inv_cov = R @ torch.diag_embed(1 / scales**2) @ R.transpose(1, 2)  # (N, 3, 3)
    cov = R @ torch.diag_embed(scales**2) @ R.transpose(1, 2)
    ext = 3 * torch.sqrt(torch.diagonal(cov, dim1=1, dim2=2))  # (N, 3)
    lo, hi = means - ext, means + ext
    o = origins[:, None, None, :]                      # (M, 1, 1, 3)
    d = dirs[:, :, None, :]                            # (M, D, 1, 3)
    with torch.no_grad():
        inv_d = 1 / d
        ta, tb = (lo - o) * inv_d, (hi - o) * inv_d
        t0 = torch.clamp(torch.minimum(ta, tb).amax(-1), min=0)
        t1 = torch.maximum(ta, tb).amin(-1)
        hit = t0 <= t1                                  # (M, D, N)
        mvec = means[None, None] - o                    # (M, 1, N, 3)
        ad = torch.einsum("nij,mdj->mdni", inv_cov, dirs)
        am = torch.einsum("nij,mknj->mkni", inv_cov, mvec)
        a = (d * ad).sum(-1)
        bb = (d * am).sum(-1)
        c = (mvec * am).sum(-1)
        tt = torch.where(bb > 0, bb / a, torch.zeros_like(bb))
        q = torch.clamp(c - 2 * tt * bb + tt * tt * a, min=0)
        alpha = opacity * torch.exp(-0.5 * q)
        alpha = torch.where(alpha < ALPHA_MIN, torch.zeros_like(alpha),
                            torch.clamp(alpha, max=ALPHA_MAX))
        own = torch.arange(N, device=exclude.device)[None, None, :] == exclude[:, None, None]
        alpha = torch.where(hit & ~own, alpha, torch.zeros_like(alpha))
        trans = torch.prod(1 - alpha, dim=-1)           # (M, D)
        w = local[:, 2]
        return (trans * w).sum(-1) / w.sum()
