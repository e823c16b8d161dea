"""What a relight renders and how, typed once (torch-free): `Light`, and `RelightSettings`, the
parameters `dgs relight` and the service's render jobs share. The command line adds what only a
local user may name (`core.relight.run.RelightParams`: a camera path file, a capture-light map
file); the service adds its own reading of `envmap` (an asset id or a built-in map,
`worker.pipelines.RelightJobParams`)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    ConfigDict,
    Field,
    field_validator,
    model_serializer,
    model_validator,
)
from pydantic_core import PydanticCustomError

from core.config.base import FRAMES, AsTuple, FrameSlice, StrictModel

__all__ = ["BUILTIN_ENVMAPS", "FRAMES", "FrameSlice", "Light", "RelightSettings"]
# The built-in maps of core.relight.presets (a test keeps the two equal).
BUILTIN_ENVMAPS = ("studio", "sunset", "neon")

Coordinate = Annotated[float, Field(ge=-1e6, le=1e6, allow_inf_nan=False)]
Channel = Annotated[float, Field(ge=0, le=1e6, allow_inf_nan=False)]
Vec3 = Annotated[tuple[Coordinate, Coordinate, Coordinate], AsTuple]


class Light(StrictModel):
    """A light added to the environment: it adds `intensity * color * max(0, n . l)` of
    irradiance, a point light's falling off as 1/d^2 (docs/design.md 5.8)."""

    model_config = ConfigDict(frozen=True)

    kind: Literal["directional", "point"] = Field(
        "directional", description="directional (infinitely far) or point.")
    direction: Vec3 | None = Field(
        None, description="Directional lights: the direction towards the light, capture world "
                          "coordinates (need not be unit length; not zero).")
    position: Vec3 | None = Field(
        None, description="Point lights: the light's position, capture world coordinates.")
    color: Annotated[tuple[Channel, Channel, Channel], AsTuple] = Field(
        (1.0, 1.0, 1.0), description="Linear RGB tint (not all zero).")
    intensity: float = Field(
        1.0, le=1e6, allow_inf_nan=False, json_schema_extra={"exclusiveMinimum": 0},
        description="Irradiance scale, > 0 (pi lights a surface facing the light as brightly "
                    "as a uniform environment of radiance 1); at distance 1 for a point light.")

    @field_validator("intensity")
    @classmethod
    def _positive(cls, value: float) -> float:
        if not value > 0:
            raise PydanticCustomError(
                "light_intensity", "a light needs an intensity > 0 (one of {value} adds "
                "nothing; leave the light out instead)", {"value": value})
        return value

    @field_validator("color")
    @classmethod
    def _some_color(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        if max(value) <= 0:
            raise PydanticCustomError("light_color", "a light's color must not be all zero "
                                      "(it would add nothing)")
        return value

    @model_serializer(mode="wrap")
    def _without_unused(self, handler) -> dict[str, Any]:
        """The stored form names only the direction or the position it uses."""
        return {k: v for k, v in handler(self).items() if v is not None}

    @model_validator(mode="after")
    def _placed(self) -> Light:
        need, other = (("direction", "position") if self.kind == "directional"
                       else ("position", "direction"))
        if getattr(self, need) is None:
            raise PydanticCustomError("light_placement", "a {kind} light needs '{need}'",
                                      {"kind": self.kind, "need": need})
        if getattr(self, other) is not None:
            raise PydanticCustomError("light_placement", "a {kind} light takes '{need}', not "
                                      "'{other}'", {"kind": self.kind, "need": need,
                                                    "other": other})
        if self.kind == "directional" and max(abs(x) for x in self.direction) < 1e-9:
            raise PydanticCustomError("light_direction", "a directional light's direction "
                                      "must not be zero")
        return self

    @property
    def vector(self) -> tuple[float, float, float]:
        """The direction towards a directional light, or a point light's position."""
        return self.direction if self.kind == "directional" else self.position


class RelightSettings(StrictModel):
    """What to relight and how: an environment map turned and exposed, lights, the views."""

    envmap: str | None = Field(
        None, min_length=1, max_length=4096,
        description="The environment map (equirectangular .exr or .hdr), or a built-in map: "
                    + ", ".join(f"builtin:{n}" for n in BUILTIN_ENVMAPS) + ". Without one the "
                    "environment is black and the lights alone light the render (then at "
                    "least one light is required).")
    rotation_deg: float = Field(
        0.0, ge=-360, le=360, allow_inf_nan=False,
        description="Turn of the map about the capture's up axis, degrees (right-hand rule).")
    exposure: float = Field(0.0, ge=-20, le=20, allow_inf_nan=False,
                            description="Map exposure in stops (radiance x 2**exposure).")
    lights: Annotated[tuple[Light, ...], AsTuple] = Field(
        (), max_length=64, description="Lights added to the map.")
    cameras: str = Field(
        "heldout", min_length=1, max_length=4096,
        description="heldout (every 8th capture camera), all, or camera ids ID,ID,... "
                    "(ignored with an orbit or a camera path).")
    frames: FrameSlice | None = Field(
        None, description="Python slice over the reconstruction's finished frames, e.g. '0:10' "
                          "or '2'; all by default.")
    orbit: int | None = Field(
        None, ge=1, le=720,
        description="Render this many views on an orbit around the subject instead of the "
                    "capture's cameras, and an MP4 per frame (relit/<frame>.mp4).")
    fps: float = Field(24.0, gt=0, le=240, allow_inf_nan=False,
                       description="Frame rate of the MP4s.")
    ao: bool = Field(True, description="Shade with the learnt ambient occlusion (False: the "
                                       "no-AO baseline).")

    @field_validator("envmap")
    @classmethod
    def _builtin_known(cls, value: str | None) -> str | None:
        if value is not None and value.startswith("builtin:") and \
                value.removeprefix("builtin:") not in BUILTIN_ENVMAPS:
            raise PydanticCustomError(
                "envmap_builtin", "envmap: no built-in map {name} (built-in: {known})",
                {"name": value, "known": ", ".join(f"builtin:{n}" for n in BUILTIN_ENVMAPS)})
        return value

    @model_validator(mode="after")
    def _something_lights(self) -> RelightSettings:
        if self.envmap is None and not self.lights:
            raise PydanticCustomError(
                "light_required", "envmap, lights: give an environment map or at least one "
                "light; with neither nothing lights the render")
        return self
