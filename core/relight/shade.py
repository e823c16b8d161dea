"""Deferred shading of a G-buffer under new light (docs/design.md section 5):

    albedo = base / max(visibility, 0.05) / E_capture(n)
    output = albedo * (visibility * E_env(n) + sum_lights intensity * colour * max(0, n . l))
             + residual

E_env is the SH9 irradiance of the environment map. E_capture is the capture's irradiance:
uniform (docs/design.md's default) or, this project's extension, the SH9 irradiance of the stage's
lighting, which undoes a directional key light that no constant can (docs/benchmarks.md).
`ao=False` is the no-AO baseline: visibility = 1 in the shading term (the albedo is still
divided by the visibility the model learnt).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from core.relight.envmap import A_HAT, irradiance_sh9
from core.relight.gbuffer import GBuffer
from core.config.relight import Light
from core.relight.lights import CaptureLight

__all__ = ["MIN_VISIBILITY", "Shading", "capture_irradiance", "light_irradiance", "shade"]

# docs/design.md section 5: the albedo divides by max(visibility, 0.05).
MIN_VISIBILITY = 0.05
# E_capture is floored at this fraction of its mean over the sphere: a normal the stage light
# barely reached carries no albedo information, and dividing by ~0 would blow its noise up.
MIN_CAPTURE_FRACTION = 0.05


@dataclass
class Shading:
    """The shaded view."""

    linear: Tensor
    """(H, W, 3) straight linear colour of the surface (0 where uncovered)."""
    alpha: Tensor
    """(H, W, 1) coverage to composite it with."""
    albedo: Tensor
    """(H, W, 3) the albedo estimate."""


def capture_irradiance(normal: Tensor, light: CaptureLight) -> Tensor:
    """E_capture at unit normals (H, W, 3) -> (H, W, 3), floored (MIN_CAPTURE_FRACTION)."""
    if light.sh9 is None:
        return torch.full_like(normal, float(light.uniform))
    coeffs = torch.as_tensor(light.sh9, dtype=normal.dtype, device=normal.device)
    # Mean irradiance over the sphere is the DC term: A_0 L_00 Y_00 = pi * L_00 / (2 sqrt(pi)).
    mean = coeffs[0] * float(A_HAT[0]) * 0.5 / np.sqrt(np.pi)
    floor = (MIN_CAPTURE_FRACTION * mean).clamp_min(1e-6)
    return torch.maximum(irradiance_sh9(normal, coeffs), floor)


def light_irradiance(normal: Tensor, points: Tensor, lights: Sequence[Light]) -> Tensor:
    """Sum over lights of intensity * colour * max(0, n . l) [/ d^2 for point lights] (H, W, 3)."""
    out = torch.zeros_like(normal)
    for light in lights:
        color = normal.new_tensor(light.color) * float(light.intensity)
        v = normal.new_tensor(light.vector)
        if light.kind == "directional":
            cos = (normal * (v / v.norm())).sum(-1, keepdim=True)
            falloff = 1.0
        else:
            to_light = v - points
            dist2 = (to_light * to_light).sum(-1, keepdim=True).clamp_min(1e-8)
            cos = (normal * to_light).sum(-1, keepdim=True) / dist2.sqrt()
            falloff = 1.0 / dist2
        out = out + color * cos.clamp_min(0.0) * falloff
    return out


def shade(g: GBuffer, env_sh9: np.ndarray | Tensor, capture: CaptureLight,
          lights: Sequence[Light] = (), *, ao: bool = True) -> Shading:
    """Relight one G-buffer under the environment's SH9 radiance (9, 3) plus `lights`."""
    env = torch.as_tensor(env_sh9, dtype=g.normal.dtype, device=g.normal.device)
    covered = (g.normal.abs().sum(-1, keepdim=True) > 0) & (g.alpha > 0)
    albedo = g.base / g.visibility.clamp_min(MIN_VISIBILITY) / capture_irradiance(g.normal,
                                                                                 capture)
    vis = g.visibility if ao else torch.ones_like(g.visibility)
    light = vis * irradiance_sh9(g.normal, env) + light_irradiance(g.normal, g.points, lights)
    out = albedo * light + g.residual
    out = torch.where(covered, out.clamp_min(0.0), torch.zeros_like(out))
    return Shading(linear=out, alpha=g.alpha, albedo=torch.where(covered, albedo, 0.0))
