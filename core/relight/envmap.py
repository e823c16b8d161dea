"""Environment maps: reading (OpenEXR, Radiance HDR), validation, the capture's up axis, and
their 9-coefficient spherical-harmonic irradiance (Ramamoorthi & Hanrahan 2001, "An Efficient
Representation for Irradiance Environment Maps").

Layout (the one `dgs synth` writes to gt/envmaps/): equirectangular radiance, row r at polar
angle theta = pi (r + 0.5) / H from the up axis, column c at azimuth phi = 2 pi (c + 0.5) / W
measured from the frame's first axis e1 towards e2 (:func:`up_frame`; for up = +z that is from +x
towards +y). `rotation_deg` turns the environment about the up axis by the right-hand rule: what
was at azimuth phi appears at phi + rotation.

SH coefficients are radiance coefficients L_lm in world coordinates, in the real-SH order and
signs of core.synth.shading (Y00, Y1-1 ~ y, Y10 ~ z, Y11 ~ x, Y2-2 ~ xy, Y2-1 ~ yz, Y20, Y21 ~ xz,
Y22 ~ x^2 - y^2), so gt/lights.json's `sh9_radiance` plugs in directly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.data.images import ImageReadError, read_image
from core.relight.presets import builtin_radiance, is_builtin

__all__ = [
    "A_HAT",
    "EnvMap",
    "check_radiance",
    "equirect_directions",
    "irradiance_sh9",
    "load_envmap",
    "project_sh9",
    "read_envmap",
    "sh9_basis",
    "up_frame",
]

# Clamped-cosine convolution weights per band (Ramamoorthi & Hanrahan 2001, eq. 8): exact for
# radiance band-limited to l <= 2 (Funk-Hecke).
A_HAT = np.array([math.pi] + [2 * math.pi / 3] * 3 + [math.pi / 4] * 5)

# Real SH normalisation constants (Ramamoorthi & Hanrahan 2001, eq. 3), written exactly.
_Y0 = 0.5 / math.sqrt(math.pi)
_Y1 = math.sqrt(3 / (4 * math.pi))
_Y2 = 0.5 * math.sqrt(15 / math.pi)
_Y20 = 0.25 * math.sqrt(5 / math.pi)
_Y22 = 0.25 * math.sqrt(15 / math.pi)


def sh9_basis(d):
    """Real SH basis (..., 9) at unit directions (..., 3); numpy arrays or torch tensors."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    terms = [x * 0 + _Y0, _Y1 * y, _Y1 * z, _Y1 * x, _Y2 * x * y, _Y2 * y * z,
             _Y20 * (3 * z * z - 1), _Y2 * x * z, _Y22 * (x * x - y * y)]
    if isinstance(d, np.ndarray):
        return np.stack(terms, axis=-1)
    # lazy: the API reads maps with this module and must not load torch
    import torch

    return torch.stack(terms, dim=-1)


def irradiance_sh9(normals, coeffs):
    """Irradiance E(n) (..., 3) at unit normals (..., 3) from radiance coefficients (9, 3),
    clamped at 0 (SH9 can ring below zero opposite strong lights). numpy or torch alike."""
    weights = coeffs * (A_HAT[:, None] if isinstance(coeffs, np.ndarray)
                        else coeffs.new_tensor(A_HAT)[:, None])
    e = sh9_basis(normals) @ weights
    return e.clip(min=0.0) if isinstance(e, np.ndarray) else e.clamp_min(0.0)


def up_frame(up) -> np.ndarray:
    """(3, 3) rows e1, e2, u: a right-handed frame about the unit up axis u; e1 is the world axis
    most perpendicular to u (x first on ties) made orthogonal to it, e2 = u x e1. For up = +z this
    is the identity (azimuth from +x towards +y, as gt/lights.json says)."""
    u = np.asarray(up, dtype=np.float64).reshape(3)
    norm = float(np.linalg.norm(u))
    if not np.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"up: expected a non-zero 3-vector, got {list(u)}")
    u = u / norm
    axis = np.eye(3)[int(np.argmin(np.abs(u) + np.array([0.0, 1e-9, 2e-9])))]
    e1 = axis - (axis @ u) * u
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(u, e1), u])


def equirect_directions(height: int, width: int, up=(0.0, 0.0, 1.0),
                        rotation_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """World directions (H, W, 3) of the pixel centres and their solid angles (H, W) (sum 4 pi
    up to the discretisation: sin(theta) dtheta dphi per pixel)."""
    frame = up_frame(up)
    theta = (np.arange(height) + 0.5) / height * math.pi
    phi = (np.arange(width) + 0.5) / width * 2 * math.pi + math.radians(rotation_deg)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    local = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)
    d_omega = np.sin(t) * (math.pi / height) * (2 * math.pi / width)
    return local @ frame, d_omega


def project_sh9(radiance: np.ndarray, up=(0.0, 0.0, 1.0), rotation_deg: float = 0.0) -> np.ndarray:
    """(9, 3) radiance SH coefficients L_lm = sum L(w) Y_lm(w) dw of an equirectangular map
    (H, W, 3), pixels weighted by their solid angle."""
    h, w = radiance.shape[:2]
    dirs, d_omega = equirect_directions(h, w, up, rotation_deg)
    basis = sh9_basis(dirs.reshape(-1, 3)) * d_omega.reshape(-1, 1)
    return basis.T @ radiance.reshape(-1, 3).astype(np.float64)


@dataclass(frozen=True)
class EnvMap:
    """A validated environment map, exposure applied, with its SH9 radiance about `up`."""

    path: str
    """The file it was read from."""
    radiance: np.ndarray
    """(H, W, 3) float32 linear radiance, exposure applied, W = 2 H."""
    up: tuple[float, float, float]
    """The capture's up axis the map's poles sit on."""
    rotation_deg: float
    """Turn about `up` (right-hand rule) applied when projecting."""
    exposure: float
    """Stops applied: radiance x 2**exposure."""
    sh9: np.ndarray
    """(9, 3) radiance SH coefficients in world coordinates."""


def read_envmap(path: Path, max_pixels: int | None = None) -> np.ndarray:
    """Decode an .exr or .hdr map (RGB order), header checked first (core.data.images);
    ImageReadError otherwise, its message without the path."""
    path = Path(path)
    if path.suffix.lower() not in (".exr", ".hdr"):
        raise ImageReadError(path, f"unsupported file type {path.suffix!r} (expected .exr or "
                                   ".hdr)")
    return read_image(path, max_pixels)


def _read(path: Path) -> np.ndarray:
    try:
        return read_envmap(path)
    except ImageReadError as exc:
        raise ValueError(f"envmap: {path}: {exc.message}") from None


def check_radiance(image: np.ndarray, where: str) -> np.ndarray:
    """The RGB radiance (H, W, 3) of a decoded map, or ValueError naming `where` and the problem:
    not RGB, not 2:1 equirectangular, NaN/Inf or negative pixels, all zero."""
    if image.ndim != 3 or image.shape[2] < 3:
        raise ValueError(f"envmap: {where}: has {1 if image.ndim == 2 else image.shape[2]} "
                         "channel(s); an environment map needs RGB")
    h, w = image.shape[:2]
    if w != 2 * h or h < 2:
        raise ValueError(f"envmap: {where}: is {w}x{h}; an equirectangular map is twice as wide "
                         "as it is high (e.g. 1024x512)")
    rgb = np.asarray(image[..., :3], dtype=np.float32)
    bad = ~np.isfinite(rgb).all(axis=-1)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise ValueError(f"envmap: {where}: {int(bad.sum())} pixel(s) are NaN or Inf (first at "
                         f"row {r}, column {c}); fix or clamp the map")
    # Maps resampled with a sharpening filter (Poly Haven's, Blender's) ring a little below 0
    # beside bright lights: a few 1e-7..2e-3 in maps whose mean is ~1. That is not light taken
    # away, so it is clamped; a negative beyond 1% of the mean radiance is refused.
    tolerance = 0.01 * float(np.abs(rgb).mean())
    if (rgb < -tolerance).any():
        raise ValueError(f"envmap: {where}: {int((rgb < -tolerance).any(axis=-1).sum())} "
                         "pixel(s) are negative; radiance must be >= 0")
    rgb = np.maximum(rgb, 0.0)
    if not (rgb > 0).any():
        raise ValueError(f"envmap: {where}: every pixel is zero (no light)")
    return rgb


def load_envmap(path, up=(0.0, 0.0, 1.0), rotation_deg: float = 0.0,
                exposure: float = 0.0) -> EnvMap:
    """Read and validate an equirectangular .exr or .hdr map (or a built-in one, 'builtin:NAME',
    core.relight.presets); errors name the file and the problem."""
    for name, value in (("rotation_deg", rotation_deg), ("exposure", exposure)):
        if not math.isfinite(float(value)):
            raise ValueError(f"{name}: expected a finite number, got {value!r}")

    if is_builtin(path):  # builtin:studio, builtin:sunset, builtin:neon (core.relight.presets)
        rgb = builtin_radiance(str(path))
    else:
        path = Path(path)
        rgb = check_radiance(_read(path), str(path))
    rgb = rgb * np.float32(2.0 ** float(exposure))
    frame = up_frame(up)  # validates `up`
    return EnvMap(str(path), rgb, tuple(float(v) for v in frame[2]), float(rotation_deg),
                  float(exposure), project_sh9(rgb, frame[2], rotation_deg))
