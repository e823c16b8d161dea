"""Ambient occlusion by ray tracing through Gaussians (docs/design.md section 5).

From each origin, `n_dirs` rays leave over the Fibonacci hemisphere about its normal; along each
ray, T = prod (1 - alpha) over the Gaussians whose 3-sigma box the ray meets, alpha taken at the
ray's closest approach to the Gaussian; visibility = cosine-weighted mean of T. Not
differentiable: it bakes a training target and the visibility initialisation.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from native._backend import load
from native.reference import trace_visibility as reference

__all__ = ["trace_visibility", "gaussian_rays", "gaussian_visibility"]


def _check(name: str, t: object, shape: tuple[int | None, ...], dtype=None) -> Tensor:
    if not isinstance(t, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != len(shape) or any(e is not None and s != e for s, e in zip(t.shape, shape)):
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    if dtype is not None and t.dtype != dtype:
        raise ValueError(f"{name} must have dtype {dtype}, got {t.dtype}")
    if t.is_floating_point() and t.numel() and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or Inf values")
    return t


def trace_visibility(origins: Tensor, normals: Tensor, means: Tensor, quats: Tensor,
                     scales: Tensor, opacity: Tensor, *, n_dirs: int = 64,
                     exclude: Tensor | None = None, offset: float | Tensor = 0.0,
                     backend: Literal["native", "reference"] = "native") -> Tensor:
    """Visibility (M,) in [0, 1] of M points with unit normals, occluded by N Gaussians.

    origins, normals: (M, 3); means (N, 3), quats (N, 4) w,x,y,z, scales (N, 3) positive,
    opacity (N,) in [0, 1] (the geometry opacity); exclude (M,) int64: one Gaussian each origin
    ignores (the Gaussian it sits on), -1 for none. offset: a distance (scalar or (M,)) by which
    each origin moves along its normal before tracing, so that rays leaving a surface do not
    start inside the thin Gaussians that make that surface (self-intersection).
    """
    m = origins.shape[0] if isinstance(origins, Tensor) and origins.dim() == 2 else -1
    _check("origins", origins, (None, 3))
    _check("normals", normals, (m, 3))
    _check("means", means, (None, 3))
    n = means.shape[0]
    _check("quats", quats, (n, 4))
    _check("scales", scales, (n, 3))
    _check("opacity", opacity, (n,))
    dtype = origins.dtype
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"origins must be float32 or float64, got {dtype}")
    for name, t in (("normals", normals), ("means", means), ("quats", quats), ("scales", scales),
                    ("opacity", opacity)):
        if t.dtype != dtype:
            raise ValueError(f"{name} must have dtype {dtype} like origins, got {t.dtype}")
    if n and bool((scales <= 0).any()):
        raise ValueError("scales must be positive")
    if n and bool(((opacity < 0) | (opacity > 1)).any()):
        raise ValueError("opacity must lie in [0, 1]")
    if m and bool(((normals.norm(dim=-1) - 1).abs() > 1e-3).any()):
        raise ValueError("normals must be unit vectors")
    if isinstance(n_dirs, bool) or not isinstance(n_dirs, int) or n_dirs < 1:
        raise ValueError(f"n_dirs must be a positive integer, got {n_dirs!r}")
    device = origins.device
    if exclude is None:
        exclude = torch.full((m,), -1, dtype=torch.int64, device=device)
    _check("exclude", exclude, (m,), torch.int64)
    for name, t in (("normals", normals), ("means", means), ("quats", quats), ("scales", scales),
                    ("opacity", opacity), ("exclude", exclude)):
        if t.device != device:
            raise ValueError(f"{name} is on {t.device} but origins is on {device}; "
                             "every tensor must be on one device")
    offset = torch.as_tensor(offset, dtype=dtype, device=device)
    if offset.dim() not in (0, 1) or (offset.dim() == 1 and offset.shape[0] != m):
        raise ValueError(f"offset must be a scalar or have shape ({m},), got {tuple(offset.shape)}")
    if not bool(torch.isfinite(offset).all()) or bool((offset < 0).any()):
        raise ValueError("offset must be finite and >= 0")
    origins = origins + (offset[:, None] if offset.dim() else offset) * normals
    if backend == "reference":
        return reference(origins, normals, means, quats, scales, opacity, n_dirs=n_dirs,
                         exclude=exclude)
    if backend != "native":
        raise ValueError(f"backend must be 'native' or 'reference', got {backend!r}")

    if device.type == "cuda":
        if not getattr(load(), "has_cuda", lambda: False)():
            raise ValueError(f"origins is on {device} but the native extension was built without "
                             "CUDA; move the tensors to the CPU or pass backend='reference'")
    elif device.type != "cpu":
        raise ValueError(f"origins is on {device}; the native ray tracer runs on the CPU or CUDA")
    c = lambda t: t.detach().contiguous()  # noqa: E731
    return load().trace_visibility(c(origins), c(normals), c(means), c(quats), c(scales),
                                   c(opacity), c(exclude), n_dirs)


def gaussian_rays(means: Tensor, scales: Tensor) -> tuple[Tensor, Tensor]:
    """Where the rays of `gaussian_visibility` start, as `trace_visibility` takes them: offset
    (N,) three of each Gaussian's shortest standard deviations along its normal (out of the
    shell of neighbours of the same thickness that overlap it on a surface) and exclude (N,)
    the Gaussian itself."""
    return (3 * scales.detach().amin(dim=-1),
            torch.arange(means.shape[0], dtype=torch.int64, device=means.device))


def gaussian_visibility(means: Tensor, quats: Tensor, scales: Tensor, opacity: Tensor,
                        normals: Tensor, *, n_dirs: int = 64,
                        backend: Literal["native", "reference"] = "native") -> Tensor:
    """Per-Gaussian visibility (N,): rays about each Gaussian's normal from its centre, moved
    and excluding itself as `gaussian_rays` says (the initialisation of the visibility
    attribute)."""
    offset, exclude = gaussian_rays(means, scales)
    return trace_visibility(means, normals, means, quats, scales, opacity, n_dirs=n_dirs,
                            exclude=exclude, offset=offset, backend=backend)
