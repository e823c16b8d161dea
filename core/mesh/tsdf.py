"""Truncated signed distance fusion of depth maps (Curless & Levoy 1996; KinectFusion's projective
TSDF, Newcombe et al. 2011), vectorized in torch on whatever device the volume lives on.

The grid is dense but processed in chunks of voxels, every camera per chunk, so the temporaries
stay at `chunk` voxels whatever the grid size; the grid itself is two float32 values and two
flags per voxel (a 512-voxel scene diagonal is at most 296^3 = 26M voxels for a cube, 260 MB).

Per camera and voxel (projective distance along the optical axis, sdf = depth - z):
- projected between four pixels with valid depth: sdf (depth interpolated bilinearly) >
  -truncation updates the running weighted mean of clip(sdf / truncation, -1, 1) (free space in
  front of the surface counts as +1; behind it, occluded, nothing is learnt);
- projected between four pixels without surface (background: the geometry branch is
  transparent there): the voxel is outside for good (+1), a visual-hull carve (space carving,
  Kutulakos & Seitz 2000); carved voxels leave the working set, so later views only visit the
  hull, a several-fold saving since the hull fills a small part of the box;
- on a silhouette (the four pixels disagree) or outside the image: nothing.
After fusion a voxel nobody observed is inside (-1) when some camera's view contains it (it is
behind every surface that saw it) and outside (+1) when none does. Unseen space is not surface,
though: below the lowest observed surface (along the capture's up axis) an unobserved voxel is
outside, so a subject filmed only from above is closed at its lowest visible surface instead of
standing on the cone of its silhouettes down to the box.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

__all__ = ["LOW_SURFACE_QUANTILE", "TSDFVolume"]

LOW_SURFACE_QUANTILE = 0.001
"""The share of observed surface voxels allowed below the floor `TSDFVolume.values` closes at."""


def _sample_depth(depth: Tensor, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Depth at continuous pixel coordinates (x, y) (pixel centres at +0.5), bilinear between
    the four nearest pixel centres; returns (depth, all four have a surface, none has). Bilinear
    matters at grazing angles, where depth changes by a lot across one pixel; a voxel whose four
    pixels disagree sits on a silhouette and is left unobserved by this view, which would
    otherwise carve up to a pixel's footprint off the surface."""
    h, w = depth.shape
    flat = depth.reshape(-1)
    xf, yf = x - 0.5, y - 0.5
    x0, y0 = xf.floor(), yf.floor()
    fx, fy = xf - x0, yf - y0
    # Border voxels read the nearest in-image pixels (clamped), as the edge of the view.
    xa, ya = x0.long().clamp(0, w - 1), y0.long().clamp(0, h - 1)
    xb, yb = (x0.long() + 1).clamp(0, w - 1), (y0.long() + 1).clamp(0, h - 1)
    d00, d01 = flat[ya * w + xa], flat[ya * w + xb]
    d10, d11 = flat[yb * w + xa], flat[yb * w + xb]
    full = (d00 > 0) & (d01 > 0) & (d10 > 0) & (d11 > 0)
    empty = (d00 <= 0) & (d01 <= 0) & (d10 <= 0) & (d11 <= 0)
    bil = (d00 * (1 - fx) + d01 * fx) * (1 - fy) + (d10 * (1 - fx) + d11 * fx) * fy
    return bil, full, empty


@dataclass
class TSDFVolume:
    """A dense TSDF grid over the box [lo, hi] with cubic voxels; voxel (i, j, k) has its centre
    at lo + (i + 0.5, j + 0.5, k + 0.5) * voxel."""

    lo: np.ndarray
    """(3,) box corner (world)."""
    voxel: float
    """Voxel edge length (world units)."""
    shape: tuple[int, int, int]
    """Voxels along x, y, z."""
    truncation: float
    """Truncation distance (world units)."""
    tsdf: Tensor
    """(X, Y, Z) running mean of the truncated distance / truncation, in [-1, 1]."""
    weight: Tensor
    """(X, Y, Z) observations so far."""
    seen: Tensor
    """(X, Y, Z) bool: inside some camera's view."""
    carved: Tensor
    """(X, Y, Z) bool: projects onto background in some view (outside the visual hull)."""
    chunk: int = 1 << 20
    """Voxels per vectorized step (bounds temporary memory)."""

    @classmethod
    def create(cls, lo, hi, voxel: float, truncation_voxels: float = 5.0, *,
               device: str | torch.device = "cpu", chunk: int = 1 << 20) -> TSDFVolume:
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        if not (voxel > 0 and np.all(hi > lo)):
            raise ValueError(f"box, voxel: expected hi > lo and voxel > 0, got lo={lo}, hi={hi}, "
                             f"voxel={voxel}")
        if truncation_voxels <= 0:
            raise ValueError(f"truncation: expected > 0 voxels, got {truncation_voxels}")
        shape = tuple(int(n) for n in np.maximum(np.ceil((hi - lo) / voxel), 1))
        if int(np.prod(shape)) > 400_000_000:
            raise ValueError(f"voxel: {voxel:g} makes {shape} voxels; use a coarser resolution")
        z = lambda dtype: torch.zeros(shape, dtype=dtype, device=device)  # noqa: E731
        return cls(lo, float(voxel), shape, float(truncation_voxels * voxel),
                   z(torch.float32), z(torch.float32), z(torch.bool), z(torch.bool), chunk)

    def _centres(self, idx: Tensor) -> Tensor:
        """World centres (n, 3) of the flat voxel indices `idx`, float32."""
        dev = self.tsdf.device
        X, Y, Z = self.shape
        ijk = torch.stack([idx // (Y * Z), (idx // Z) % Y, idx % Z], dim=1).float()
        return (ijk + 0.5) * self.voxel + torch.as_tensor(self.lo, dtype=torch.float32,
                                                          device=dev)

    @torch.no_grad()
    def integrate(self, depths: list[Tensor], K: list[Tensor], viewmats: list[Tensor]) -> None:
        """Fuse depth maps (H, W) (0 or less: no surface at that pixel) seen by cameras with
        intrinsics K (3, 3) and world-to-camera `viewmats` (4, 4) (OpenCV axes)."""
        if not (len(depths) == len(K) == len(viewmats)):
            raise ValueError(f"depths, K, viewmats: expected equal lengths, got {len(depths)}, "
                             f"{len(K)}, {len(viewmats)}")
        dev = self.tsdf.device
        cams = [(d.to(dev, torch.float32), k.to(dev, torch.float32),
                 v.to(dev, torch.float32)) for d, k, v in zip(depths, K, viewmats)]
        tsdf, weight, seen = self.tsdf.view(-1), self.weight.view(-1), self.seen.view(-1)
        carved = self.carved.view(-1)
        for start in range(0, tsdf.numel(), self.chunk):
            stop = min(start + self.chunk, tsdf.numel())
            # Voxels still undecided; a carved one leaves the set, so the views after the first
            # few only visit the visual hull and its surroundings.
            idx = torch.arange(start, stop, device=dev)[~carved[start:stop]]
            pts = self._centres(idx)
            acc = torch.zeros(len(idx), device=dev)
            cnt = torch.zeros(len(idx), device=dev)
            hit = torch.zeros(len(idx), dtype=torch.bool, device=dev)
            for depth, k, viewmat in cams:
                if len(idx) == 0:
                    break
                obs, valid, inside, empty = self._observe(pts, depth, k, viewmat)
                acc += torch.where(valid, obs, 0.0)
                cnt += valid.float()
                hit |= inside
                if empty.any():
                    carved[idx[empty]] = True
                    seen[idx[empty]] = True
                    keep = ~empty
                    idx, pts, acc, cnt, hit = (t[keep] for t in (idx, pts, acc, cnt, hit))
            w = weight[idx]
            tsdf[idx] = torch.where(cnt > 0, (tsdf[idx] * w + acc) / (w + cnt).clamp_min(1e-6),
                                    tsdf[idx])
            weight[idx] = w + cnt
            seen[idx] |= hit

    def _observe(self, pts: Tensor, depth: Tensor, K: Tensor,
                 viewmat: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Per voxel: (observation in [-1, 1], whether it counts, whether the voxel is in view,
        whether it projects onto background only, a carve)."""
        h, w = depth.shape
        cam = torch.addmm(viewmat[:3, 3], pts, viewmat[:3, :3].T)
        z = cam[:, 2]
        zs = z.clamp_min(1e-6)
        x = (K[0, 0] * cam[:, 0] + K[0, 1] * cam[:, 1]) / zs + K[0, 2]
        y = K[1, 1] * cam[:, 1] / zs + K[1, 2]
        inside = (z > 1e-6) & (x >= 0) & (x < w) & (y >= 0) & (y < h)
        d, surface, empty = _sample_depth(depth, x, y)
        sdf = d - z
        obs = (sdf / self.truncation).clamp(-1.0, 1.0)
        valid = inside & surface & (sdf > -self.truncation)
        return obs, valid, inside, inside & empty

    def values(self, up=None) -> np.ndarray:
        """(X, Y, Z) float32 signed field for marching cubes: the fused mean where observed,
        else -1 inside some view and +1 outside every view; with `up` (3,) also +1 where
        unobserved below the lowest observed surface (module docstring)."""
        unobserved = torch.where(self.seen, -1.0, 1.0)
        if up is not None:
            unobserved = torch.where(self._below_surface(up), 1.0, unobserved)
        fused = torch.where(self.weight > 0, self.tsdf, unobserved)
        return torch.where(self.carved, 1.0, fused).cpu().numpy()

    def _below_surface(self, up) -> Tensor:
        """(X, Y, Z) bool: voxel centres lower along `up` than every observed surface voxel
        (fused, within a voxel of the surface), less `LOW_SURFACE_QUANTILE` of them (a stray
        depth does not lower the floor)."""
        dev = self.tsdf.device
        u = torch.as_tensor(np.asarray(up, np.float64) / np.linalg.norm(up), dtype=torch.float32,
                            device=dev)
        axes = [torch.arange(n, device=dev, dtype=torch.float32) for n in self.shape]
        lo = torch.as_tensor(self.lo, dtype=torch.float32, device=dev)
        h = sum(((a + 0.5) * self.voxel + lo[i]).view(*[-1 if j == i else 1 for j in range(3)])
                * u[i] for i, a in enumerate(axes))
        surface = (self.weight > 0) & (self.tsdf.abs() * self.truncation < self.voxel)
        if not bool(surface.any()):
            return torch.zeros(self.shape, dtype=torch.bool, device=dev)
        floor = torch.quantile(h.expand(self.shape)[surface].float()[:2**24],
                               LOW_SURFACE_QUANTILE)
        return h.expand(self.shape) < floor
