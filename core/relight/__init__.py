"""Relighting (docs/design.md section 5): environment maps and their SH9 irradiance, lights, the
deferred shading of a reconstruction's G-buffer, camera paths, image and video output, and
`relight_run`, the entry point of `dgs relight` and of the service's render jobs.

The submodules that need torch (gbuffer, shade, run, sheet, metrics) are imported on use.
"""

from __future__ import annotations

from typing import Any

from core.relight.envmap import (
    EnvMap,
    equirect_directions,
    irradiance_sh9,
    load_envmap,
    project_sh9,
    sh9_basis,
    up_frame,
)
from core.relight.lights import CaptureLight, load_capture_light, parse_light

__all__ = [
    "CaptureLight",
    "EnvMap",
    "RelightParams",
    "RelightProgress",
    "RelightStopped",
    "equirect_directions",
    "irradiance_sh9",
    "load_capture_light",
    "load_envmap",
    "parse_light",
    "project_sh9",
    "relight_run",
    "sh9_basis",
    "up_frame",
]

_LAZY = {"RelightParams", "RelightProgress", "RelightStopped", "relight_run"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        # lazy: the API process reads environment maps with this package and loads no torch
        from core.relight import run

        return getattr(run, name)
    raise AttributeError(f"module 'core.relight' has no attribute {name!r}")
