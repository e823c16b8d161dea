"""The pipelines a job can run, each registered here once (`PIPELINES`): its parameters as a
pydantic model (published as JSON Schema by `GET /v1/pipelines`), the request that submits it,
what it runs on, the execution that runs it on a worker, the artifact kinds it writes and its
time limits. Nothing else in the code names a pipeline: the routers find theirs by endpoint
(`submitted_at`), a source job is judged by `makes_results`, and `core.rundir` classifies files
by kind only (`tests/worker/test_pipelines.py` holds both to it). Torch-free: the API
validates a job's parameters here before it is queued; the worker runs it (`worker.runner`).

`reconstruct` runs on a capture (POST /v1/jobs), which the API resolves into the run the job
stores (`core.config.ResolvedRun`); `relight` and `export` on the results of a succeeded
reconstruction (POST /v1/renders, /v1/exports name it; the job row keeps it as
`source_job_id`)."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, WithJsonSchema

from core.config import (
    CheckpointEvery,
    GopSize,
    Preset,
    ResolvedRun,
    RunConfig,
    load_config,
    resolve_run,
    schema,
    validate,
)
from core.config.base import FrameSlice, StrictModel
from core.data.capture import Capture
from core.config.relight import BUILTIN_ENVMAPS, Light, RelightSettings
from worker.settings import WorkerSettings

__all__ = ["BUILTIN_ENVMAPS", "DEFAULT_PIPELINE", "ExportJobParams", "Light", "MODEL_KIND",
           "PIPELINES", "Pipeline", "ReconstructParams", "RelightJobParams", "get_pipeline",
           "makes_results", "submitted_at"]

# The asset kind of a tenant's own normal-prior model (TorchScript or ONNX), which a
# reconstruction names by id as `config.normal_estimator`.
MODEL_KIND = "normal_model"


class ReconstructParams(StrictModel):
    """Parameters of `reconstruct` (the `dgs reconstruct` command line, docs/design.md 3.2)."""

    # frozen: the configuration `run_config` resolved stays the parameters' own (the rest of
    # the configuration is StrictModel's, which pydantic merges in)
    model_config = ConfigDict(frozen=True)

    preset: Preset = Field(
        "fast", description="Training schedule: paper (30k steps per key frame), fast (7.5k), "
                            "test (500, for checks).")
    frames: FrameSlice | None = Field(
        None, description="Python slice over the capture's frame list, e.g. '0:10'; all by "
                          "default.")
    gop: GopSize | None = Field(
        None, description="Frames per group of pictures; default: config.gop (20 unless set).")
    checkpoint_every: CheckpointEvery | None = Field(
        None, description="Steps between checkpoints (a lost worker's job resumes from the "
                          "last); default: the preset's.")
    config: Annotated[dict[str, Any], WithJsonSchema(schema(RunConfig, inline=True))] = Field(
        default_factory=dict,
        description="Overrides of the preset's configuration, in the shape of RUN/config.json's "
                    "`config` (e.g. {\"train\": {\"seed\": 3}}); every key, type and bound is "
                    "checked, and the run resolved against the capture, before the job is made "
                    "(422 naming the setting).")

    _resolved: RunConfig | None = PrivateAttr(None)

    def run_config(self) -> RunConfig:
        """The configuration these parameters ask for: the preset, `config`, then
        `checkpoint_every` and `gop` (core.config.ConfigError naming each bad setting under
        'config'); resolved once per object."""
        if self._resolved is None:
            overrides = dict(self.config)
            if self.checkpoint_every is not None:
                overrides["checkpoint_every"] = self.checkpoint_every
            self._resolved = load_config(self.preset, overrides=overrides, gop=self.gop,
                                         where="config")
        return self._resolved

    def resolve(self, capture: Capture, *, capture_name: str,
                has_masks: bool | None = None) -> ResolvedRun:
        """The run these parameters ask for on `capture` (`core.config.resolve_run`:
        ConfigError naming `frames`, `config.split`, `config.mesh.subject` when the capture
        cannot run it). The API makes it once, at submit, and stores it with the job; the
        worker runs the stored one."""
        return resolve_run(capture, self.run_config(), preset=self.preset, frames=self.frames,
                           capture_name=capture_name, has_masks=has_masks)


class RelightJobParams(RelightSettings):
    """Parameters of `relight` (`dgs relight`'s, `core.config.relight.RelightSettings`, less
    what names a file on the server): relit renders of a succeeded reconstruction under an
    environment map and added lights. `envmap` is an envmap asset id (POST /v1/assets) or a
    built-in map."""

    capture_light: float | None = Field(
        None, gt=0, le=1e6, allow_inf_nan=False,
        description="Uniform irradiance the capture was lit with, which the albedo is divided "
                    "by; default pi (a white dome of radiance 1).")

    @property
    def envmap_asset(self) -> str | None:
        """The envmap asset id the render uses (None: a built-in map or none)."""
        return None if self.envmap is None or self.envmap.startswith("builtin:") \
            else self.envmap


class ExportJobParams(StrictModel):
    """Parameters of `export` (the `dgs export` command line): a succeeded reconstruction's
    frames as PLY, SPZ or the relightable sequence stream the web page plays."""

    formats: list[Literal["ply", "spz", "stream"]] = Field(
        ["stream"], min_length=1, max_length=3,
        description="ply (the frame PLYs), spz (one SPZ per frame), stream "
                    "(export/stream.dgss, range-requestable, docs/stream.md).")
    frames: FrameSlice | None = Field(
        None, description="Python slice over the reconstruction's frames; all by default.")
    fps: float | None = Field(None, gt=0, le=240, allow_inf_nan=False,
                              description="The stream's frame rate (default: the capture's, "
                                          "else 24).")
    position_tolerance: float | None = Field(
        None, gt=0, lt=0.01, allow_inf_nan=False,
        description="Stream: largest centre error as a fraction of a group's bounding-box "
                    "diagonal (default 1e-4).")
    subject: bool = Field(
        False, description="Only the subject: the Gaussians inside the hull of the capture's "
                           "masks (the performers without the stage); the capture needs masks.")


@dataclass(frozen=True)
class Pipeline:
    """A pipeline, registered once in `PIPELINES`: everything the API and the worker need to
    know of it."""

    name: str
    description: str
    params: type[BaseModel]
    execution: str
    """What runs a job of it on a worker ("module:Class", imported by `execution_class` on a
    worker only: it needs torch, which the API never loads)."""
    endpoint: str
    """The request that submits a job of it (POST)."""
    artifacts: tuple[str, ...]
    """Kinds of artifact the pipeline writes (`core.rundir.classify` names a file's kind)."""
    soft_limit: str
    """The WorkerSettings field that holds the soft time limit in seconds."""
    source: Literal["capture", "job"] = "capture"
    """What a job of it runs on: a capture (whose run the API resolves and stores with the job)
    or the succeeded job of a pipeline that runs on a capture (`makes_results`)."""
    check: Callable[[Any], Any] | None = None
    """Checks across the parameters beyond their schema (ValueError with `details`)."""

    def schema(self) -> dict[str, Any]:
        return self.params.model_json_schema()

    def execution_class(self) -> type:
        """The class `execution` names, imported (on a worker: it loads torch)."""
        module, name = self.execution.split(":")
        return getattr(importlib.import_module(module), name)

    def parse(self, params: Any, where: str = "params") -> BaseModel:
        """The parameters from JSON data (a request's, or a job row's), validated strictly
        (`core.config.validate`): core.config.ConfigError naming each bad one under `where`."""
        return validate(self.params, params, where)

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
        execution="worker.reconstruct_job:ReconstructJob",
        endpoint="/v1/jobs",
        artifacts=("ply", "mesh", "render", "normal", "ao", "depth", "relit", "plot", "config",
                   "metrics", "eval", "image"),
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
        execution="worker.relight_job:RelightJob",
        endpoint="/v1/renders",
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
        execution="worker.export_job:ExportJob",
        endpoint="/v1/exports",
        artifacts=("stream", "spz", "ply", "export"),
        soft_limit="export_soft_limit_seconds",
        source="job",
    ),
}


DEFAULT_PIPELINE = "reconstruct"
"""What POST /v1/jobs runs when its body names no pipeline."""


def get_pipeline(name: str) -> Pipeline:
    if name not in PIPELINES:
        raise ValueError(f"pipeline: expected one of {sorted(PIPELINES)}, got {name!r}")
    return PIPELINES[name]


def submitted_at(endpoint: str) -> Pipeline:
    """The pipeline whose jobs the request POST `endpoint` submits (the first registered, when
    several are: `pipeline` in the request picks another)."""
    for pipeline in PIPELINES.values():
        if pipeline.endpoint == endpoint:
            return pipeline
    raise ValueError(f"endpoint: no pipeline is submitted at {endpoint!r}")


def makes_results(name: str) -> bool:
    """Whether a job of pipeline `name` is a reconstruction: one run on a capture, whose
    succeeded results the pipelines run on a job (`Pipeline.source` "job") take."""
    return name in PIPELINES and PIPELINES[name].source == "capture"
