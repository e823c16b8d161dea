"""Response bodies of what the server says about itself: health, readiness, `/v1/info` (its
limits, tus endpoint, pipelines and formats) and `/v1/pipelines`."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

__all__ = ["HealthOut", "InfoOut", "LimitsOut", "PipelineOut", "ReadyOut", "TusOut"]


class LimitsOut(BaseModel):
    max_file_bytes: int
    max_capture_bytes: int
    max_capture_files: int
    max_path_bytes: int
    max_archive_bytes: int
    max_archive_members: int
    max_asset_bytes: int
    max_json_bytes: int = Field(description="Largest JSON request body but a manifest's.")
    max_manifest_bytes: int = Field(description="Largest body of a capture manifest "
                                                "(POST /v1/captures, PATCH its manifest).")
    max_json_file_bytes: int = Field(description="Largest .json file in a capture.")
    max_image_pixels: int = Field(description="Largest image (width x height) accepted in a "
                                              "capture or as an environment map.")
    max_active_jobs: int = Field(description="Most queued or running jobs of one tenant.")
    max_event_streams: int = Field(description="Most open event streams of one tenant on one "
                                               "API process, and most opened at once.")
    event_streams_per_minute: float = Field(description="Event streams one tenant may open a "
                                                        "minute on one API process, once "
                                                        "max_event_streams are spent.")
    job_changes_per_minute: float = Field(description="Job submits, cancels, retries and "
                                                      "deletes of one tenant a minute, once "
                                                      "job_changes_burst are spent.")
    job_changes_burst: int


class TusOut(BaseModel):
    endpoint: str
    version: str
    extensions: list[str]
    checksum_algorithms: list[str]
    max_size: int


class PipelineOut(BaseModel):
    name: str
    description: str
    params_schema: dict[str, Any] = Field(description="JSON Schema of the params object.")
    artifact_kinds: list[str]


class InfoOut(BaseModel):
    version: str
    tenant: str
    keys_required: bool
    limits: LimitsOut
    tus: TusOut
    pipelines: list[str]
    capture_formats: dict[str, str] = Field(
        description="Source formats a capture may be uploaded in (besides canonical and auto), "
                    "each with what it reads.")
    jobs: dict[str, int] = Field(description="The caller's jobs per state.")
    retention_days: float | None


class HealthOut(BaseModel):
    status: Literal["ok"]


class ReadyOut(BaseModel):
    status: Literal["ready", "unavailable"]
    checks: dict[str, str]
