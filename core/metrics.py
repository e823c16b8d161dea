"""Image and normal metrics shared by training (running PSNR), `dgs eval` and the relight
scores: one definition each."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from core.losses import ssim

__all__ = ["normal_agreement", "psnr", "psnr_of_mse", "rgb_scores"]


def psnr_of_mse(mse: float) -> float:
    """PSNR (dB) of a mean squared error of images in 0..1 (100 for a perfect match)."""
    return 100.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def psnr(pred: Tensor, target: Tensor) -> float:
    """Peak signal-to-noise ratio (dB) of images in 0..1."""
    return psnr_of_mse(float((pred.detach() - target).square().mean()))


def rgb_scores(rgb: np.ndarray, target: np.ndarray, foreground: np.ndarray) -> dict:
    """{"psnr" over `foreground` (H, W) pixels (None when the view has none: nothing to score,
    and means skip it), "psnr_full" over the image, "ssim" (11x11 Gaussian window) over the
    image} of images (H, W, 3) in 0..1."""
    err = (rgb - target) ** 2
    return {"psnr": psnr_of_mse(float(err[foreground].mean())) if foreground.any() else None,
            "psnr_full": psnr_of_mse(float(err.mean())),
            "ssim": float(ssim(torch.from_numpy(np.ascontiguousarray(rgb, np.float32)),
                               torch.from_numpy(np.ascontiguousarray(target, np.float32))))}


def normal_agreement(pred_png: np.ndarray, reference: np.ndarray,
                     foreground: np.ndarray) -> tuple[float, float] | None:
    """(mean cosine, mean angle in degrees) between normals stored as (n+1)/2 (black: none) and
    unit `reference` normals (H, W, 3) over `foreground` (H, W) pixels; None when no pixel."""
    if not foreground.any():
        return None
    covered = pred_png.max(axis=-1) > 0
    n = pred_png * 2.0 - 1.0
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
    cos = np.where(covered, np.clip((n * reference).sum(-1), -1.0, 1.0), 0.0)[foreground]
    return float(cos.mean()), float(np.degrees(np.arccos(cos)).mean())
