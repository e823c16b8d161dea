"""Native-vs-reference comparison used by the tests and by benchmarks/rasterizer.py --check.

The native op runs in float32; the reference runs in float64 on the same (upcast) values, so the
measured error is the native op's error against the exact math. Errors are relative to the
largest magnitude of each tensor: max |native - reference| / max |reference|.

The blending rule is discontinuous (skip below alpha 1/255, clamp at 0.99, stop below T 1e-4).
Where the exact value of one of those tests lies within float32 rounding of its threshold, a
float32 implementation may legitimately decide the other way and change that pixel by up to
1/255. Image outputs are therefore compared on the pixels where no decision is that close
(`ambiguous` counts the others; it is a handful in a scene, often zero). Gradients are compared
in full.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from native import rasterize
from native import reference as ref_module
from native.reference import rasterize as reference

__all__ = ["Comparison", "compare", "rel_err", "OUTPUTS"]

OUTPUTS = ("color", "geometry", "depth", "alpha_c", "alpha_g", "means2d", "contribution")


def rel_err(a: Tensor, b: Tensor) -> float:
    a, b = a.detach().double(), b.detach().double()
    scale = float(b.abs().max()) if b.numel() else 0.0
    diff = float((a - b).abs().max()) if b.numel() else 0.0
    return diff / scale if scale > 0 else diff


@dataclass
class Comparison:
    forward: dict[str, float] = field(default_factory=dict)
    grads: dict[str, float] = field(default_factory=dict)
    ambiguous: int = 0  # pixels left out of the image comparison (see module docstring)

    def worst(self) -> tuple[float, float]:
        return max(self.forward.values(), default=0.0), max(self.grads.values(), default=0.0)


AMBIGUITY = 2e-5  # relative distance to a threshold that float32 rounding can cross


def ambiguous(scene64, beta: float = 0.0, eps2d: float = 0.3, antialiased: bool = False,
              near: float = 0.01, far: float = 1e10, **_) -> tuple[Tensor, Tensor]:
    """(H, W) pixels and (N,) Gaussians with a blending decision within float32 reach of its
    threshold."""
    s = scene64
    with torch.no_grad():
        p, m2, cov, comp, valid = ref_module._project(s.means, s.quats, s.scales, s.viewmat, s.K,
                                                      s.width, s.height, eps2d, antialiased,
                                                      near, far)
        idx = torch.nonzero(valid).squeeze(1)
        idx = idx[torch.sort(p[idx, 2], stable=True).indices]
        v, u = torch.meshgrid(torch.arange(s.height, dtype=torch.float64),
                              torch.arange(s.width, dtype=torch.float64), indexing="ij")
        pix = torch.stack([u.reshape(-1) + 0.5, v.reshape(-1) + 0.5], -1)
        d = pix[None] - m2[idx][:, None]
        inv = torch.linalg.inv(cov[idx])
        e = -0.5 * torch.einsum("npi,nij,npj->np", d, inv, d)
        amb = torch.zeros(pix.shape[0], dtype=torch.bool)
        amb_g = torch.zeros(s.means.shape[0], dtype=torch.bool)
        for o in (0.5 * comp * ((1 + beta) * s.opacity_c + (1 - beta) * s.opacity_g),
                  0.5 * comp * ((1 - beta) * s.opacity_c + (1 + beta) * s.opacity_g)):
            raw = o[idx][:, None] * torch.exp(e)
            near_min = (raw / ref_module.ALPHA_MIN - 1).abs() < AMBIGUITY
            near_max = (raw / ref_module.ALPHA_MAX - 1).abs() < AMBIGUITY
            alpha = torch.clamp(raw, max=ref_module.ALPHA_MAX)
            alpha = torch.where(alpha >= ref_module.ALPHA_MIN, alpha, torch.zeros_like(alpha))
            trans = torch.cumprod(1 - alpha, dim=0)
            near_stop = (trans / ref_module.T_MIN - 1).abs() < AMBIGUITY
            pair = near_min | near_max | near_stop
            amb |= pair.any(dim=0)
            amb_g[idx] |= pair.any(dim=1)
        return amb.reshape(s.height, s.width), amb_g


def _image_err(a: Tensor, b: Tensor, keep: Tensor) -> float:
    if a.dim() == 3 and a.shape[:2] == keep.shape:
        return rel_err(a[keep], b[keep])
    return rel_err(a, b)


def _loss(out, weights: dict[str, Tensor]) -> Tensor:
    total = out.color.new_zeros(())
    for name, w in weights.items():
        total = total + (getattr(out, name) * w.to(out.color.dtype)).sum()
    return total


def compare(scene, *, seed: int = 0, background: Tensor | None = None,
            geometry_branch: bool = True, dtype: torch.dtype = torch.float32,
            **kw) -> Comparison:
    """Run both implementations on `scene` with a random linear loss on every output; the
    native op in `dtype` (float32, or float64 for an exact check of the algorithm)."""
    scene = scene.to(torch.float32)  # the values both sides start from
    s32 = scene.to(dtype).requires_grad_()
    s64 = scene.to(torch.float64).requires_grad_()
    bg32 = bg64 = None
    if background is not None:
        bg32 = background.detach().float().to(dtype).clone().requires_grad_()
        bg64 = background.detach().double().clone().requires_grad_()
    args32, args64 = list(s32.args()), list(s64.args())
    if not geometry_branch:
        args32[6] = args64[6] = None
    o32 = rasterize(*args32, background=bg32, **kw)
    o64 = reference(*args64, background=bg64, **kw)
    result = Comparison()
    amb_pix, amb_gauss = ambiguous(s64, **kw) if s32.means.dtype != s64.means.dtype else (
        torch.zeros(s64.height, s64.width, dtype=torch.bool),
        torch.zeros(s64.means.shape[0], dtype=torch.bool))
    keep, keep_g = ~amb_pix, ~amb_gauss
    result.ambiguous = int(amb_pix.sum())
    for name in OUTPUTS:
        result.forward[name] = _image_err(getattr(o32, name), getattr(o64, name), keep)
    result.forward["radii_mismatch"] = float((o32.radii != o64.radii).sum())

    g = torch.Generator().manual_seed(seed + 1000)
    weights = {name: torch.randn(getattr(o64, name).shape, generator=g, dtype=torch.float64)
               for name in ("color", "geometry", "depth", "alpha_c", "alpha_g", "means2d")}
    _loss(o32, weights).backward()
    _loss(o64, weights).backward()
    tensors32, tensors64 = s32.float_tensors(), s64.float_tensors()
    if not geometry_branch:
        tensors32.pop("geometry")
        tensors64.pop("geometry")
    n = s64.means.shape[0]
    for name, t in tensors32.items():
        g32, g64 = t.grad, tensors64[name].grad
        if g64.dim() and g64.shape[0] == n and name not in ("viewmat", "K"):
            g32, g64 = g32[keep_g], g64[keep_g]
        result.grads[name] = rel_err(g32, g64)
    if bg32 is not None:
        result.grads["background"] = rel_err(bg32.grad, bg64.grad)
    result.grads["absgrad_c"] = rel_err(o32.absgrad_c[keep_g], o64.absgrad_c[keep_g])
    result.grads["absgrad_g"] = rel_err(o32.absgrad_g[keep_g], o64.absgrad_g[keep_g])
    result.grads["means2d.grad"] = rel_err(o32.means2d.grad[keep_g], o64.means2d.grad[keep_g])
    return result
