"""Lights added to the environment (directional and point), and the capture's own lighting that
the albedo is divided by.

A light adds irradiance `intensity * colour * max(0, n . l)` at a surface point with unit normal
n, l the unit direction towards the light; a point light's falls off as 1 / d^2 with the distance
d from the surface point (from the depth buffer) to the light. Units are those of the environment
map's irradiance, so a directional light of intensity pi lights a surface facing it as brightly as
a uniform environment of radiance 1 does.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from core.config.relight import Light
from core.relight.envmap import load_envmap

__all__ = ["CaptureLight", "load_capture_light", "parse_light"]


def _vec3(value, where: str, *, nonzero: bool = False) -> tuple[float, float, float]:
    try:
        v = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected 3 numbers, got {value!r}") from None
    if len(v) != 3 or not all(math.isfinite(x) for x in v):
        raise ValueError(f"{where}: expected 3 finite numbers, got {value!r}")
    if nonzero and math.hypot(*v) < 1e-12:
        raise ValueError(f"{where}: expected a non-zero direction, got {list(v)}")
    return v  # type: ignore[return-value]


def parse_light(spec: str) -> Light:
    """`directional:X,Y,Z:INTENSITY[:R,G,B]` or `point:X,Y,Z:INTENSITY[:R,G,B]` (the CLI form);
    ValueError saying what is wrong."""
    parts = spec.split(":")
    if len(parts) not in (3, 4) or parts[0] not in ("directional", "point"):
        raise ValueError(f"--light: expected directional:X,Y,Z:INTENSITY[:R,G,B] or "
                         f"point:X,Y,Z:INTENSITY[:R,G,B], got {spec!r}")
    try:
        intensity = float(parts[2])
    except ValueError:
        raise ValueError(f"--light: intensity must be a number, got {parts[2]!r}") from None
    color = _vec3(parts[3].split(","), "--light color") if len(parts) == 4 else (1.0, 1.0, 1.0)
    place = "direction" if parts[0] == "directional" else "position"
    try:
        return Light(kind=parts[0], intensity=intensity, color=color,
                     **{place: _vec3(parts[1].split(","), f"--light {parts[0]} {place}")})
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(map(str, first["loc"]))
        raise ValueError(f"--light {spec}: " + (f"{where}: " if where else "")
                         + first["msg"].removeprefix("Value error, ")) from None


@dataclass(frozen=True)
class CaptureLight:
    """The lighting the capture was filmed under, which the albedo is divided by."""

    uniform: float | None
    """Uniform irradiance (docs/design.md section 5's default); None when `sh9` is given."""
    sh9: np.ndarray | None
    """(9, 3) radiance SH of the stage's lighting (this project's extension, see
    docs/benchmarks.md): the albedo is divided by its irradiance E_capture(n)."""
    source: str
    """Where it came from, for the record."""


# Irradiance of a uniform environment of radiance 1 (E = pi L): a capture lit evenly by a white
# dome of unit radiance keeps its colours when relit under a unit-radiance map.
DEFAULT_UNIFORM = math.pi


def load_capture_light(spec: str | float | None, up=(0.0, 0.0, 1.0)) -> CaptureLight:
    """None: uniform pi; a number: uniform irradiance; a .exr/.hdr: the stage's environment map;
    a .json: {"sh9_radiance": 9x3} or a synthetic capture's gt/lights.json (its `images` light)."""
    if spec is None:
        return CaptureLight(DEFAULT_UNIFORM, None, "uniform (default)")
    try:
        value = float(spec)
    except (TypeError, ValueError):
        value = None
    if value is not None:
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"capture_light: a uniform irradiance must be > 0, got {spec!r}")
        return CaptureLight(value, None, f"uniform {value:g}")
    path = Path(str(spec))
    if path.suffix.lower() in (".exr", ".hdr"):
        return CaptureLight(None, load_envmap(path, up).sh9, f"envmap {path}")
    if path.suffix.lower() != ".json":
        raise ValueError(f"capture_light: expected a number, an .exr/.hdr map or a .json with "
                         f"sh9_radiance, got {spec!r}")
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"capture_light: cannot read {path}: {exc}") from None
    if "lights" in doc and "images" in doc:  # gt/lights.json of `dgs synth`
        doc = doc["lights"].get(doc["images"], {})
    sh = np.asarray(doc.get("sh9_radiance", []), dtype=np.float64)
    if sh.shape != (9, 3) or not np.isfinite(sh).all():
        raise ValueError(f"capture_light: {path} has no finite 9x3 'sh9_radiance'")
    return CaptureLight(None, sh, f"sh9 {path}")
