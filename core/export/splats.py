"""`Splats`: one frame's Gaussians as activated numpy arrays, the common currency of the export
formats (PLY, SPZ, the sequence stream), with the conversions to and from a frame PLY
(docs/design.md 3.3: raw logits and log-scales) and the uniform quantizer the compact formats use.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from core.plyio import read_gaussian_ply, read_track_ids, write_gaussian_ply

__all__ = ["SH_REST", "Splats", "dequantize", "quantize", "read_frame_ply", "write_frame_ply"]

SH_REST = 15
"""Higher SH coefficients per channel a frame carries (degree 3)."""
_EPS = 1e-6  # opacities and visibilities are clamped into (eps, 1 - eps) before the logit


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p.astype(np.float64), _EPS, 1 - _EPS)
    return np.log(p / (1 - p)).astype(np.float32)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return (1 / (1 + np.exp(-x.astype(np.float64)))).astype(np.float32)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return (v / np.where(n > 0, n, 1)).astype(np.float32)


@dataclass
class Splats:
    """N Gaussians, activated: what a renderer uses. Quaternions are w, x, y, z with w >= 0."""

    means: np.ndarray
    """(N, 3) float32 centres."""
    scales: np.ndarray
    """(N, 3) float32 log-scales (as stored: the renderer takes exp)."""
    quats: np.ndarray
    """(N, 4) float32 unit quaternions w, x, y, z, w >= 0."""
    opacity_c: np.ndarray
    """(N,) float32 appearance opacity 0..1."""
    opacity_g: np.ndarray
    """(N,) float32 geometry opacity 0..1."""
    sh0: np.ndarray
    """(N, 3) float32 degree-0 SH coefficient per channel (colour = 0.5 + SH_C0 * sh0)."""
    shN: np.ndarray
    """(N, 15, 3) float32 higher SH coefficients, coefficient-major."""
    normals: np.ndarray
    """(N, 3) float32 unit geometry-branch normals."""
    visibility: np.ndarray
    """(N,) float32 ambient visibility 0..1."""
    ids: np.ndarray
    """(N,) int64 track ids (equal for the same Gaussian in every frame of a group)."""

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def take(self, index: np.ndarray) -> Splats:
        """The Gaussians at `index` (an index array or a boolean mask), in that order."""
        return Splats(**{k: getattr(self, k)[index] for k in self.__dataclass_fields__})

    def canonical(self) -> Splats:
        """Unit quaternions with w >= 0 and unit normals (q and -q are one rotation)."""
        q = _unit(self.quats)
        q = np.where(q[:, :1] < 0, -q, q)
        return replace(self, quats=q, normals=_unit(self.normals))

    def to_params(self):
        """Raw torch parameters for `core.plyio.write_gaussian_ply` / `GaussianModel`."""
        def t(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

        return {"means": t(self.means), "scales": t(self.scales), "quats": t(self.quats),
                "sh0": t(self.sh0[:, None, :]), "shN": t(self.shN),
                "opacity_c": t(_logit(self.opacity_c)), "opacity_g": t(_logit(self.opacity_g)),
                "normals": t(self.normals), "visibility": t(_logit(self.visibility)[:, None])}

    @classmethod
    def from_params(cls, params, ids: np.ndarray | None = None) -> Splats:
        """From raw parameters (names of `core.model.PARAM_NAMES`, torch tensors or arrays)."""
        def a(name: str) -> np.ndarray:
            v = params[name]
            v = v.detach().cpu().numpy() if hasattr(v, "detach") else np.asarray(v)
            return v.astype(np.float32)

        n = a("means").shape[0]
        return cls(means=a("means"), scales=a("scales"), quats=a("quats"),
                   opacity_c=_sigmoid(a("opacity_c").reshape(n)),
                   opacity_g=_sigmoid(a("opacity_g").reshape(n)),
                   sh0=a("sh0").reshape(n, 3), shN=a("shN").reshape(n, SH_REST, 3),
                   normals=a("normals"), visibility=_sigmoid(a("visibility").reshape(n)),
                   ids=np.arange(n, dtype=np.int64) if ids is None
                   else np.asarray(ids, np.int64)).canonical()


def read_frame_ply(path: str | os.PathLike[str]) -> Splats:
    """A frame PLY (docs/design.md 3.3) with its track ids (0..N-1 when it has none)."""
    return Splats.from_params(read_gaussian_ply(path), read_track_ids(path))


def write_frame_ply(path: str | os.PathLike[str], splats: Splats) -> None:
    """The frame PLY of `splats`, with track ids, atomically."""
    write_gaussian_ply(Path(path), splats.to_params(), splats.ids)


def quantize(values: np.ndarray, lo, step, bits: int) -> np.ndarray:
    """Codes round((v - lo) / step) clipped to 0 .. 2^bits - 1, as uint16 (uint32 past 16 bits)."""
    top = (1 << bits) - 1
    codes = np.rint((values.astype(np.float64) - lo) / step)
    return np.clip(codes, 0, top).astype(np.uint16 if bits <= 16 else np.uint32)


def dequantize(codes: np.ndarray, lo, step) -> np.ndarray:
    """float32 lo + code * step (the decoders in Python and in the page compute the same)."""
    return (np.asarray(lo, np.float32) + codes.astype(np.float32) * np.asarray(step, np.float32)
            ).astype(np.float32)
