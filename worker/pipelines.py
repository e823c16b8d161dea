"""The pipelines a job can run, with their parameters as pydantic models (published as JSON
Schema by `GET /v1/pipelines`) and their time limits. Torch-free: the API validates a job's
parameters here before it is queued; the worker runs it (`worker.runner`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from worker.settings import WorkerSettings

__all__ = ["PIPELINES", "Pipeline", "ReconstructParams", "get_pipeline"]


class ReconstructParams(BaseModel):
    """Parameters of `reconstruct` (the `dgs reconstruct` command line, DESIGN.md 3.2)."""

    model_config = ConfigDict(extra="forbid")

    preset: Literal["paper", "fast", "test"] = Field(
        "fast", description="Training schedule: paper (30k steps per key frame), fast (7.5k), "
                            "test (500, for checks).")
    frames: str | None = Field(
        None, pattern=r"^-?\d*(:-?\d*){0,2}$", max_length=32,
        description="Python slice over the capture's frame list, e.g. '0:10'; all by default.")
    gop: int = Field(20, ge=1, le=10_000, description="Frames per group of pictures.")
    checkpoint_every: int | None = Field(
        None, ge=1, le=1_000_000,
        description="Steps between checkpoints (a lost worker's job resumes from the last); "
                    "default: the preset's.")
    config: dict[str, Any] = Field(
        default_factory=dict,
        description="Overrides of the resolved configuration, in the shape of RUN/config.json "
                    "(e.g. {\"train\": {\"schedule\": {\"iterations\": 2000}}}); unknown keys "
                    "fail the job with a clear error.")


@dataclass(frozen=True)
class Pipeline:
    name: str
    description: str
    params: type[BaseModel]
    artifacts: tuple[str, ...]
    """Kinds of artifact the pipeline produces."""

    def schema(self) -> dict[str, Any]:
        return self.params.model_json_schema()

    def limits(self, settings: WorkerSettings) -> tuple[float, float]:
        """(soft, hard) time limits in seconds."""
        soft = settings.reconstruct_soft_limit_seconds
        return soft, soft + settings.hard_limit_margin_seconds


PIPELINES: dict[str, Pipeline] = {
    "reconstruct": Pipeline(
        name="reconstruct",
        description="Reconstruct every selected frame of a capture: disentangled Gaussians "
                    "(PLY), held-out renders (rgb, normal, AO, depth), metrics, plots.",
        params=ReconstructParams,
        artifacts=("ply", "render", "depth", "plot", "metrics", "config", "eval", "image"),
    ),
}


def get_pipeline(name: str) -> Pipeline:
    if name not in PIPELINES:
        raise ValueError(f"pipeline: expected one of {sorted(PIPELINES)}, got {name!r}")
    return PIPELINES[name]
