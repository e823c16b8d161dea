"""Built-in environment maps, for users without an HDR of their own and for the contact sheet's
three relit columns: `builtin:studio`, `builtin:sunset`, `builtin:neon` wherever an environment
map file is accepted.

Each is an equirectangular radiance map in the up frame of core.relight.envmap (row 0 looks
straight up), made of a sky/ground gradient and a few soft lights (lobes exp((cos - 1) / w)
about their directions). Every map is scaled so that its mean radiance is 1, which makes the
irradiance of a surface open to the whole sphere pi on average: the capture light's default
(core.relight.lights.DEFAULT_UNIFORM), so a relit render keeps roughly the capture's exposure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["BUILTIN_PREFIX", "PRESETS", "builtin_radiance", "is_builtin"]

BUILTIN_PREFIX = "builtin:"
# 64 rows: lobes of width 0.02 (about 11 degrees) span several pixels, and SH9 needs no more.
HEIGHT = 64


@dataclass(frozen=True)
class Preset:
    description: str
    zenith: tuple[float, float, float]
    """Radiance straight up (linear RGB, before normalisation)."""
    horizon: tuple[float, float, float]
    """Radiance at the horizon."""
    ground: tuple[float, float, float]
    """Radiance from below."""
    lights: tuple[tuple[float, float, tuple[float, float, float], float], ...]
    """(elevation deg, azimuth deg, RGB peak radiance, lobe width w) per soft light."""


PRESETS: dict[str, Preset] = {
    "studio": Preset("neutral three-point studio: key high front-right, fill left, rim behind",
                     (0.55, 0.55, 0.55), (0.35, 0.35, 0.35), (0.15, 0.15, 0.15),
                     ((45.0, -40.0, (9.0, 9.0, 8.6), 0.03), (20.0, 60.0, (3.0, 3.0, 3.2), 0.05),
                      (30.0, 170.0, (4.0, 4.0, 4.0), 0.02))),
    "sunset": Preset("a low warm sun under a blue sky over warm ground",
                     (0.20, 0.32, 0.65), (0.65, 0.45, 0.35), (0.12, 0.09, 0.06),
                     ((8.0, 120.0, (40.0, 18.0, 6.0), 0.01),)),
    "neon": Preset("night club: a magenta key from one side, a cyan one from the other",
                   (0.04, 0.04, 0.06), (0.05, 0.04, 0.06), (0.02, 0.02, 0.03),
                   ((15.0, 90.0, (10.0, 0.8, 8.0), 0.04), (15.0, -90.0, (0.6, 8.0, 10.0), 0.04))),
}


def is_builtin(name) -> bool:
    return str(name).startswith(BUILTIN_PREFIX)


def builtin_radiance(name: str) -> np.ndarray:
    """(64, 128, 3) float32 radiance of `builtin:<preset>` (or the bare preset name)."""
    key = str(name)[len(BUILTIN_PREFIX):] if is_builtin(name) else str(name)
    if key not in PRESETS:
        raise ValueError(f"envmap: no built-in map {key!r} (built-in: "
                         f"{', '.join(BUILTIN_PREFIX + k for k in PRESETS)})")
    p = PRESETS[key]
    h, w = HEIGHT, 2 * HEIGHT
    theta = (np.arange(h) + 0.5) / h * math.pi
    phi = (np.arange(w) + 0.5) / w * 2 * math.pi
    t, ph = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(t) * np.cos(ph), np.sin(t) * np.sin(ph), np.cos(t)], axis=-1)
    up = d[..., 2:3]
    sky = np.where(up >= 0, (1 - up) * np.array(p.horizon) + up * np.array(p.zenith),
                   np.array(p.ground))
    for elevation, azimuth, color, width in p.lights:
        e, a = math.radians(elevation), math.radians(azimuth)
        axis = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        sky = sky + np.exp(((d @ axis)[..., None] - 1.0) / width) * np.array(color)
    weights = np.sin(t)[..., None]  # solid angle per pixel up to a constant
    mean = (sky * weights).sum((0, 1)) / weights.sum()
    return (sky / float(mean.mean())).astype(np.float32)
