"""The pipelines a job can run, with their parameters as pydantic models (published as JSON
Schema by `GET /v1/pipelines`) and their time limits. Torch-free: the API validates a job's
parameters here before it is queued; the worker runs it (`worker.runner`).

`reconstruct` runs on a capture (POST /v1/jobs); `relight` on the results of a succeeded
reconstruction (POST /v1/renders names it; the job row keeps it as `source_job_id`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    WithJsonSchema,
    field_validator,
    model_serializer,
    model_validator,
)
from pydantic_core import PydanticCustomError

from core.config import RunConfig, load_config, schema
from worker.settings import WorkerSettings

__all__ = ["BUILTIN_ENVMAPS", "ExportJobParams", "LightParams", "MODEL_KIND", "PIPELINES",
           "Pipeline", "ReconstructParams", "RelightJobParams", "get_pipeline"]

FRAMES = r"^-?\d*(:-?\d*){0,2}$"
# core.relight.presets.PRESETS, named here so that the API needs no core import (a test keeps
# the two lists equal).
BUILTIN_ENVMAPS = ("studio", "sunset", "neon")
# The asset kind of a tenant's own normal-prior model (TorchScript or ONNX), which a
# reconstruction names by id as `config.normal_estimator`.
MODEL_KIND = "normal_model"


class ReconstructParams(BaseModel):
    """Parameters of `reconstruct` (the `dgs reconstruct` command line, docs/design.md 3.2)."""

    model_config = ConfigDict(extra="forbid")

    preset: Literal["paper", "fast", "test"] = Field(
        "fast", description="Training schedule: paper (30k steps per key frame), fast (7.5k), "
                            "test (500, for checks).")
    frames: str | None = Field(
        None, pattern=FRAMES, max_length=32,
        description="Python slice over the capture's frame list, e.g. '0:10'; all by default.")
    gop: int | None = Field(
        None, ge=1, le=10_000,
        description="Frames per group of pictures; default: config.gop (20 unless set).")
    checkpoint_every: int | None = Field(
        None, ge=1, le=1_000_000,
        description="Steps between checkpoints (a lost worker's job resumes from the last); "
                    "default: the preset's.")
    config: Annotated[dict[str, Any], WithJsonSchema(schema(RunConfig, inline=True))] = Field(
        default_factory=dict,
        description="Overrides of the preset's configuration, in the shape of RUN/config.json "
                    "(e.g. {\"train\": {\"seed\": 3}}); every key, type and bound is checked "
                    "before the job is made (422 naming the setting).")

    def run_config(self) -> RunConfig:
        """The configuration this job runs with: the preset, `config`, then `checkpoint_every`
        and `gop` (core.config.ConfigError naming each bad setting under 'config')."""
        overrides = dict(self.config)
        if self.checkpoint_every is not None:
            overrides["checkpoint_every"] = self.checkpoint_every
        return load_config(self.preset, overrides=overrides, gop=self.gop, where="config")


Coordinate = Annotated[float, Field(ge=-1e6, le=1e6, allow_inf_nan=False)]
Channel = Annotated[float, Field(ge=0, le=1e6, allow_inf_nan=False)]


class LightParams(BaseModel):
    """A light added to the environment map (core.relight.LightSpec): it adds
    `intensity * color * max(0, n . l)` of irradiance, a point light's falling off as 1/d^2."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["directional", "point"] = Field(
        "directional", description="directional (infinitely far) or point.")
    direction: list[Coordinate] | None = Field(
        None, min_length=3, max_length=3,
        description="Directional lights: the direction towards the light, capture world "
                    "coordinates (need not be unit length; not zero).")
    position: list[Coordinate] | None = Field(
        None, min_length=3, max_length=3,
        description="Point lights: the light's position, capture world coordinates.")
    color: list[Channel] = Field([1.0, 1.0, 1.0], min_length=3, max_length=3,
                                 description="Linear RGB tint (not all zero).")
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
    def _some_color(cls, value: list[float]) -> list[float]:
        if max(value) <= 0:
            raise PydanticCustomError("light_color", "a light's color must not be all zero "
                                      "(it would add nothing)")
        return value

    @model_serializer(mode="wrap")
    def _without_unused(self, handler) -> dict[str, Any]:
        """The stored form names only the direction or the position it uses."""
        return {k: v for k, v in handler(self).items() if v is not None}

    @model_validator(mode="after")
    def _placed(self) -> LightParams:
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


class RelightJobParams(BaseModel):
    """Parameters of `relight` (the `dgs relight` command line, docs/design.md 3.2): relit renders
    of a succeeded reconstruction under an environment map and added lights."""

    model_config = ConfigDict(extra="forbid")

    envmap: str | None = Field(
        None, min_length=1, max_length=64,
        description="An envmap asset id (POST /v1/assets: equirectangular .exr or .hdr), or a "
                    "built-in map: " + ", ".join(f"builtin:{n}" for n in BUILTIN_ENVMAPS)
                    + ". Without one the environment is black and the lights alone light the "
                      "render (then at least one light is required).")
    rotation_deg: float = Field(
        0.0, ge=-360, le=360, allow_inf_nan=False,
        description="Turn of the map about the capture's up axis, degrees (right-hand rule).")
    exposure: float = Field(0.0, ge=-20, le=20, allow_inf_nan=False,
                            description="Map exposure in stops (radiance x 2**exposure).")
    lights: list[LightParams] = Field(default_factory=list, max_length=64,
                                      description="Lights added to the map.")
    cameras: str = Field(
        "heldout", min_length=1, max_length=4096,
        description="heldout (every 8th capture camera), all, or camera ids ID,ID,... "
                    "(ignored with orbit).")
    frames: str | None = Field(
        None, pattern=FRAMES, max_length=32,
        description="Python slice over the reconstruction's frames, e.g. '0:10' or '2'; "
                    "all by default.")
    orbit: int | None = Field(
        None, ge=1, le=720,
        description="Render this many views on an orbit around the subject instead of the "
                    "capture's cameras, and an MP4 per frame (relit/<frame>.mp4).")
    fps: float = Field(24.0, gt=0, le=240, allow_inf_nan=False,
                       description="Frame rate of the orbit MP4s.")
    ao: bool = Field(True, description="Shade with the learnt ambient occlusion (False: the "
                                       "no-AO baseline).")
    capture_light: float | None = Field(
        None, gt=0, le=1e6, allow_inf_nan=False,
        description="Uniform irradiance the capture was lit with, which the albedo is divided "
                    "by; default pi (a white dome of radiance 1).")

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
    def _something_lights(self) -> RelightJobParams:
        if self.envmap is None and not self.lights:
            raise PydanticCustomError(
                "light_required", "envmap, lights: give an environment map (an asset id or "
                "builtin:NAME) or at least one light; with neither nothing lights the render")
        return self

    @property
    def envmap_asset(self) -> str | None:
        """The envmap asset id the render uses (None: a built-in map or none)."""
        return None if self.envmap is None or self.envmap.startswith("builtin:") \
            else self.envmap


class ExportJobParams(BaseModel):
    """Parameters of `export` (the `dgs export` command line): a succeeded reconstruction's
    frames as PLY, SPZ or the relightable sequence stream the web page plays."""

    model_config = ConfigDict(extra="forbid")

    formats: list[Literal["ply", "spz", "stream"]] = Field(
        ["stream"], min_length=1, max_length=3,
        description="ply (the frame PLYs), spz (one SPZ per frame), stream "
                    "(export/stream.dgss, range-requestable, docs/stream.md).")
    frames: str | None = Field(
        None, pattern=FRAMES, max_length=32,
        description="Python slice over the reconstruction's frames; all by default.")
    fps: float | None = Field(None, gt=0, le=240, allow_inf_nan=False,
                              description="The stream's frame rate (default: the capture's, "
                                          "else 24).")
    position_tolerance: float | None = Field(
        None, gt=0, lt=0.01, allow_inf_nan=False,
        description="Stream: largest centre error as a fraction of a group's bounding-box "
                    "diagonal (default 1e-4).")


@dataclass(frozen=True)
class Pipeline:
    name: str
    description: str
    params: type[BaseModel]
    artifacts: tuple[str, ...]
    """Kinds of artifact the pipeline produces."""
    soft_limit: str
    """The WorkerSettings field that holds the soft time limit in seconds."""
    source: Literal["capture", "job"] = "capture"
    """What a job of it runs on: a capture (POST /v1/jobs) or a succeeded reconstruction
    (POST /v1/renders)."""
    check: Callable[[Any], Any] | None = None
    """Checks across the parameters beyond their schema (ValueError with `details`)."""

    def schema(self) -> dict[str, Any]:
        return self.params.model_json_schema()

    def limits(self, settings: WorkerSettings) -> tuple[float, float]:
        """(soft, hard) time limits in seconds."""
        soft = getattr(settings, self.soft_limit)
        return soft, soft + settings.hard_limit_margin_seconds


PIPELINES: dict[str, Pipeline] = {
    "reconstruct": Pipeline(
        name="reconstruct",
        description="Reconstruct every selected frame of a capture: disentangled Gaussians "
                    "(PLY), held-out renders (rgb, normal, AO, depth), metrics, plots.",
        params=ReconstructParams,
        artifacts=("ply", "render", "depth", "plot", "metrics", "config", "eval", "image"),
        soft_limit="reconstruct_soft_limit_seconds",
        check=ReconstructParams.run_config,
    ),
    "relight": Pipeline(
        name="relight",
        description="Relit renders of a succeeded reconstruction under an environment map and "
                    "lights (POST /v1/renders): relit/<frame>/<camera>.png (sRGB) and .exr "
                    "(linear); with an orbit relit/<frame>.mp4, over several frames "
                    "relit/videos/<camera>.mp4; relit/relight.json.",
        params=RelightJobParams,
        artifacts=("relit", "video", "relight"),
        soft_limit="relight_soft_limit_seconds",
        source="job",
    ),
    "export": Pipeline(
        name="export",
        description="A succeeded reconstruction delivered (POST /v1/exports): export/stream.dgss "
                    "(the relightable sequence stream), export/spz/<frame>.spz, "
                    "export/ply/<frame>.ply, export/export.json (sizes, timings).",
        params=ExportJobParams,
        artifacts=("stream", "spz", "ply", "export"),
        soft_limit="relight_soft_limit_seconds",
        source="job",
    ),
}


def get_pipeline(name: str) -> Pipeline:
    if name not in PIPELINES:
        raise ValueError(f"pipeline: expected one of {sorted(PIPELINES)}, got {name!r}")
    return PIPELINES[name]
