"""Appearance of the synthetic figure: procedural albedo, ambient occlusion, SH environment light.

Shading follows the relighting model of docs/design.md section 5 with no extra lights:
``linear = albedo * visibility * E(n)``, where E is the irradiance of a 9-coefficient real-SH
environment (Ramamoorthi & Hanrahan) and visibility is cosine-weighted ambient occlusion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.synth.raster import rasterize

__all__ = [
    "LIGHTS",
    "EnvLight",
    "albedo_at",
    "fibonacci_sphere",
    "irradiance",
    "sh9_basis",
    "vertex_visibility",
]

# Cosine-lobe convolution weights per SH band.
_A_HAT = np.array([np.pi] + [2 * np.pi / 3] * 3 + [np.pi / 4] * 5)


def sh9_basis(d: np.ndarray) -> np.ndarray:
    """Real SH basis (N, 9) of unit directions (N, 3): Y00, Y1-1, Y10, Y11, Y2-2 ... Y22."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return np.stack(
        [
            np.full_like(x, 0.282095),
            0.488603 * y,
            0.488603 * z,
            0.488603 * x,
            1.092548 * x * y,
            1.092548 * y * z,
            0.315392 * (3 * z * z - 1),
            1.092548 * x * z,
            0.546274 * (x * x - y * y),
        ],
        axis=1,
    )


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) near-uniform unit directions."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(np.maximum(0.0, 1 - z * z))
    phi = i * np.pi * (3 - np.sqrt(5))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


@dataclass(frozen=True)
class EnvLight:
    """A distant environment: a sky gradient plus a few sharp directional lights (world, z-up)."""

    name: str
    sky: tuple[float, float, float]
    """Radiance (linear RGB) arriving from straight up."""
    ground: tuple[float, float, float]
    """Radiance arriving from straight down; the sky blends linearly in cos(elevation)."""
    suns: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...]
    """(direction towards the light, RGB irradiance-scale intensity) pairs."""

    def sh9(self) -> np.ndarray:
        """(9, 3) SH radiance coefficients: the gradient projected exactly, suns as SH deltas."""
        sky, ground = np.array(self.sky), np.array(self.ground)
        coeffs = np.zeros((9, 3))
        # L(w) = (sky + ground)/2 + (sky - ground)/2 * z projects onto Y00 and Y10 only.
        coeffs[0] = (sky + ground) / 2 * np.sqrt(4 * np.pi)
        coeffs[2] = (sky - ground) / 2 * np.sqrt(4 * np.pi / 3)
        for direction, color in self.suns:
            d = np.asarray(direction, dtype=np.float64)
            coeffs += sh9_basis((d / np.linalg.norm(d))[None])[0][:, None] * np.array(color)[None]
        return coeffs

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "sky": list(self.sky),
            "ground": list(self.ground),
            "suns": [{"direction": list(d), "intensity": list(c)} for d, c in self.suns],
            "sh9_radiance": self.sh9().tolist(),
        }


LIGHTS: dict[str, EnvLight] = {
    # The light the capture is filmed under: soft studio key from front-right-above plus a fill.
    "capture": EnvLight(
        "capture",
        (0.55, 0.55, 0.58),
        (0.20, 0.19, 0.18),
        (((0.5, -0.8, 0.6), (1.1, 1.05, 1.0)), ((-0.7, -0.3, 0.2), (0.35, 0.38, 0.42))),
    ),
    # Ground truth for relighting: a low warm sun from the left-back and a cold blue sky.
    "relight": EnvLight(
        "relight", (0.25, 0.35, 0.6), (0.12, 0.08, 0.05), (((-0.8, 0.5, 0.25), (1.6, 0.9, 0.45)),)
    ),
}


def irradiance(normals: np.ndarray, sh: np.ndarray) -> np.ndarray:
    """Irradiance (N, 3) at unit normals (N, 3) from SH radiance ``sh`` (9, 3), clamped at 0."""
    return np.maximum(sh9_basis(normals) @ (sh * _A_HAT[:, None]), 0.0)


def albedo_at(rest: np.ndarray, part: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """Solid texture (N, 3) in linear RGB, evaluated at rest-pose points so it moves with the body.

    A 3D checker with per-cell colour jitter plus stripes along z: enough texture everywhere for
    photometric reconstruction, and no UV seams to get wrong.
    """
    cell = np.floor(rest * 14.0).astype(np.int64)
    checker = (cell.sum(axis=1) & 1).astype(np.float64)
    h = (cell[:, 0] * 73856093) ^ (cell[:, 1] * 19349663) ^ (cell[:, 2] * 83492791)
    jitter = ((h[:, None] >> np.array([3, 11, 19])) & 255) / 255.0 - 0.5
    stripes = 0.5 + 0.5 * np.sin(rest[:, 2] * 2 * np.pi * 9.0 + part)
    base = palette[part]
    color = base * (0.6 + 0.4 * checker[:, None]) * (0.8 + 0.2 * stripes[:, None]) + 0.12 * jitter
    return np.clip(color, 0.03, 0.9)


def vertex_visibility(
    vertices: np.ndarray,
    normals: np.ndarray,
    faces: np.ndarray,
    n_dirs: int = 64,
    resolution: int = 160,
) -> np.ndarray:
    """Cosine-weighted ambient visibility per vertex (V,), 1 = unoccluded.

    For each of ``n_dirs`` directions the mesh is rasterized orthographically along it (a shadow
    map); a vertex sees that direction when nothing in the map is in front of it. This is
    hemisphere ray casting done as ``n_dirs`` rasterizations, which numpy handles fast.
    """
    dirs = fibonacci_sphere(n_dirs)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    center, radius = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2 * 1.02
    texel = 2 * radius / resolution
    acc = np.zeros(len(vertices))
    wsum = np.zeros(len(vertices))
    for d in dirs:
        cosine = np.maximum(normals @ d, 0.0)
        e1 = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(d, e1)
        rel = vertices - center
        xy = np.stack([rel @ e1, rel @ e2], axis=1) / texel + resolution / 2
        depth = -(rel @ d)  # smaller = closer to the light direction
        frags = rasterize(xy, depth, faces, resolution, resolution, perspective=False)
        u = np.clip(xy[:, 0].astype(np.int64), 0, resolution - 1)
        v = np.clip(xy[:, 1].astype(np.int64), 0, resolution - 1)
        covered = frags.mask[v, u]
        # Slope-scaled bias: a surface seen at a grazing angle changes depth quickly across a texel.
        slope = np.sqrt(np.maximum(1 - cosine**2, 0)) / np.maximum(cosine, 0.2)
        bias = texel * (1.5 + 2.0 * slope)
        visible = ~covered | (depth <= frags.depth[v, u] + bias)
        acc += cosine * visible
        wsum += cosine
    return acc / np.maximum(wsum, 1e-12)
