"""The sRGB transfer function (IEC 61966-2-1), one codec for NumPy arrays and torch tensors (a
tensor is handled by its own methods, so this module imports no torch)."""

from __future__ import annotations

import numpy as np

__all__ = ["linear_to_srgb", "srgb_to_linear"]


def _is_tensor(x) -> bool:
    return type(x).__module__.startswith("torch")


def srgb_to_linear(x):
    """Decode sRGB values in 0..1 (clamped) to linear."""
    if _is_tensor(x):
        x = x.clamp(0.0, 1.0)
        return (x / 12.92).where(x <= 0.04045, ((x + 0.055) / 1.055) ** 2.4)
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4))


def linear_to_srgb(x):
    """Encode linear values as sRGB, clipping to 0..1 first (the clip is the tone map)."""
    if _is_tensor(x):
        x = x.clamp(0.0, 1.0)
        return (12.92 * x).where(x <= 0.0031308, 1.055 * x.clamp_min(1e-12) ** (1 / 2.4) - 0.055)
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
