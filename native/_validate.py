"""Argument checks shared by the native and the reference rasterizer: each error names the
argument, what was expected and what arrived.

Two levels: the structure (types, shapes, dtypes, devices, contiguity, scalar settings, K) costs
microseconds and is checked on every call; the values (finite, positive scales, opacities in
[0, 1], no zero quaternion) read every element and cost milliseconds per 100k Gaussians, so a
training loop checks them once per run (`values=False` afterwards). The kernels stay safe on bad
values: a non-finite Gaussian fails their range tests and is culled."""

from __future__ import annotations

import numbers

import torch
from torch import Tensor

__all__ = ["check_inputs"]


def _tensor(name: str, value: object) -> Tensor:
    if not isinstance(value, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    return value


def _shape(name: str, t: Tensor, expected: tuple[int | None, ...], text: str) -> None:
    ok = t.dim() == len(expected) and all(e is None or s == e for s, e in zip(t.shape, expected))
    if not ok:
        raise ValueError(f"{name} must have shape {text}, got {tuple(t.shape)}")


def _finite(name: str, t: Tensor) -> None:
    if t.numel() and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or Inf values")


def _int(name: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
    return int(value)


def check_inputs(means, quats, scales, opacity_c, opacity_g, colors, geometry, viewmat, K, width,
                 height, beta, eps2d, near, far, background, require_contiguous: bool,
                 values: bool = True) -> None:
    """Raise ValueError naming the first bad argument; `values=False` checks the structure
    only (see the module doc)."""
    named = {"means": means, "quats": quats, "scales": scales, "opacity_c": opacity_c,
             "opacity_g": opacity_g, "colors": colors, "viewmat": viewmat, "K": K}
    if geometry is not None:
        named["geometry"] = geometry
    if background is not None:
        named["background"] = background
    for name, value in named.items():
        _tensor(name, value)
    n = means.shape[0] if means.dim() == 2 else -1
    _shape("means", means, (None, 3), "(N, 3)")
    _shape("quats", quats, (n, 4), f"(N, 4) with N={n}")
    _shape("scales", scales, (n, 3), f"(N, 3) with N={n}")
    _shape("opacity_c", opacity_c, (n,), f"(N,) with N={n}")
    _shape("opacity_g", opacity_g, (n,), f"(N,) with N={n}")
    _shape("colors", colors, (n, None), f"(N, C) with N={n}")
    if geometry is not None:
        _shape("geometry", geometry, (n, None), f"(N, G) with N={n}")
    _shape("viewmat", viewmat, (4, 4), "(4, 4)")
    _shape("K", K, (3, 3), "(3, 3)")
    if background is not None:
        _shape("background", background, (colors.shape[1],), f"(C,) with C={colors.shape[1]}")
    dtype, device = means.dtype, means.device
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"means must be float32 (or float64), got {dtype}")
    for name, t in named.items():
        if t.dtype != dtype:
            raise ValueError(f"{name} must have dtype {dtype} like means, got {t.dtype}")
        if t.device != device:
            raise ValueError(f"{name} is on {t.device} but means is on {device}")
        if require_contiguous and not t.is_contiguous():
            raise ValueError(f"{name} must be contiguous (call .contiguous() on it)")
    _int("width", width)
    _int("height", height)
    # A few numbers each: always on the CPU; on a GPU each read would stall the step (the host
    # waits for the device), so there they are checked with the values (a loop's first render).
    small = values or device.type == "cpu"
    if small:
        for name in ("viewmat", "K", "background"):
            if name in named:
                _finite(name, named[name])
    _check_settings(beta, eps2d, near, far, K if small else None)
    if values:
        _check_values(named, scales, opacity_c, opacity_g, quats, n)


def _check_values(named: dict[str, Tensor], scales: Tensor, opacity_c: Tensor,
                  opacity_g: Tensor, quats: Tensor, n: int) -> None:
    for name, t in named.items():
        _finite(name, t)
    if n and bool((scales <= 0).any()):
        raise ValueError("scales must be positive (the activation is usually exp)")
    for name, t in (("opacity_c", opacity_c), ("opacity_g", opacity_g)):
        if n and bool(((t < 0) | (t > 1)).any()):
            raise ValueError(f"{name} must lie in [0, 1] (the activation is usually sigmoid)")
    if n and bool((quats.norm(dim=-1) == 0).any()):
        raise ValueError("quats contains a zero quaternion, which is no rotation")


def _check_settings(beta, eps2d, near, far, K: Tensor | None) -> None:
    if not 0.0 <= float(beta) <= 1.0:
        raise ValueError(f"beta must lie in [0, 1], got {beta}")
    if not float(eps2d) >= 0.0:
        raise ValueError(f"eps2d must be >= 0, got {eps2d}")
    if not 0.0 < float(near) < float(far):
        raise ValueError(f"near and far must satisfy 0 < near < far, got near={near}, far={far}")
    if K is None:
        return
    fx, fy = float(K[0, 0].detach()), float(K[1, 1].detach())
    if not (fx > 0 and fy > 0):
        raise ValueError(f"K must have positive focal lengths, got fx={fx}, fy={fy}")
