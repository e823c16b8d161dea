"""Request (…In) and response (…Out) bodies of the API; inputs and outputs never share a model,
so a field added to a response can never become settable by clients."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, AwareDatetime, BaseModel, Field, WithJsonSchema
from pydantic_core import PydanticCustomError

from core.config import schema
from core.config.base import AsTuple, StrictModel
from core.data.importers import FORMATS
from core.data.rules import unprintable_at
from service.errors import ErrorInfo
from worker.pipelines import (DEFAULT_PIPELINE, ExportJobParams, Light, ReconstructParams,
                              RelightJobParams)

__all__ = [
    "ArtifactOut", "ArtifactPage", "AssetOut", "AssetPage", "CaptureFilesOut", "CaptureIn",
    "CaptureItem", "CaptureOut", "CapturePage", "CaptureSummary", "ExportIn", "FileOut", "FilePage",
    "Format", "ImageSize", "JobIn", "JobOut", "JobPage", "JobState",
    "LightIn", "LogsOut", "ManifestFileIn", "ManifestIn", "ManifestPatchIn", "Name",
    "PATCH_FILES", "PartOut", "ProgressOut", "RenderIn", "RunOut",
    "manifest_entries",
]

# The importers' registry names the formats (core.data.importers.IMPORTERS).
Format = Literal[("canonical", *FORMATS, "auto")]  # type: ignore[valid-type]
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
CaptureState = Literal["uploading", "committing", "ready", "failed"]
FileState = Literal["received", "missing", "corrupt"]
SHA256 = r"^[0-9a-fA-F]{64}$"
PATCH_FILES = 10_000
"""Most entries one manifest patch adds (and removes)."""
MAX_NAME = 256


def _printable(value: str) -> str:
    bad = unprintable_at(value)  # the one rule, core's: importers hold source names to it too
    if bad is not None:
        raise PydanticCustomError(
            "name_printable", "a name takes printable characters only (no control, format or "
            "line-separator characters); character {at} is {char}",
            {"at": bad, "char": f"U+{ord(value[bad]):04X}"})
    return value


Name = Annotated[str, AfterValidator(_printable), Field(max_length=MAX_NAME, json_schema_extra={
    "pattern": r"^[^\u0000-\u001f\u007f-\u009f\u2028\u2029]*$"})]
"""A name a client gives an object: printable characters (str.isprintable: no control, format
or separator characters but the space), at most 256 of them; stored and shown as given."""


class _In(StrictModel):
    """A request body: validated as strictly as the run configuration (core.config.base)."""


# -- captures ------------------------------------------------------------------------------------
class ManifestFileIn(_In):
    path: str = Field(min_length=1, max_length=1024, description=(
        "Relative POSIX path inside the capture, e.g. images/000000/cam00.png."))
    size: int = Field(ge=0, le=2**63 - 1, description="Size in bytes.")
    sha256: str = Field(pattern=SHA256, description="SHA-256 of the file, hexadecimal.")


class ManifestIn(_In):
    files: list[ManifestFileIn] = Field(min_length=1, fail_fast=True)


def manifest_entries(files: list[ManifestFileIn]) -> list[dict[str, Any]]:
    """The stored form of manifest entries (digests in lower case)."""
    return [{"path": f.path, "size": f.size, "sha256": f.sha256.lower()} for f in files]


class ManifestPatchIn(_In):
    files: list[ManifestFileIn] = Field(
        default_factory=list, max_length=PATCH_FILES, fail_fast=True, description=(
            "Entries to add, or to replace (same path): a replaced file must be uploaded "
            "again."))
    remove: list[str] = Field(default_factory=list, max_length=PATCH_FILES, fail_fast=True,
                              description="Paths to drop.")


class CaptureIn(_In):
    name: Name = ""
    format: Format = Field(description=(
        "canonical (docs/design.md 3.1), an importer's format, or auto (detected at commit)."))
    manifest: ManifestIn
    expires_at: AwareDatetime | None = Field(None, description=(
        "When the capture is deleted; default: the server's retention (none: kept)."))


class CaptureFilesOut(BaseModel):
    declared: int
    declared_bytes: int
    received: int
    received_bytes: int
    missing: int = Field(description="Files not received yet (corrupt ones included).")
    missing_paths: list[str] = Field(description="The first missing files, manifest order.")
    corrupt: int = Field(description="Files whose last upload did not match the manifest.")
    corrupt_paths: list[str]


class ImageSize(BaseModel):
    width: int
    height: int
    cameras: int


class CaptureSummary(BaseModel):
    frames: int
    cameras: int
    camera_ids: list[str] | None = Field(None, description=(
        "The cameras' ids, in the capture's order (captures committed before this field "
        "existed have none)."))
    views: int
    image_sizes: list[ImageSize]
    masks: int = Field(description="Views with a foreground mask.")
    test_cameras: list[str] | None = Field(None, description=(
        "The cameras the capture declares held out (capture.json test_cameras), or null."))
    normals: int = Field(description="Views with a normal prior.")
    source_format: str
    import_warnings: list[str] = Field(default_factory=list, description=(
        "What the import changed (a mirrored world mirrored back: docs/capture-format.md)."))


class CaptureItem(BaseModel):
    id: str
    name: str
    format: str
    state: CaptureState
    total_bytes: int = Field(description="Sum of the manifest's sizes.")
    summary: CaptureSummary | None = Field(description="Once ready: what the capture holds.")
    created_at: dt.datetime
    committed_at: dt.datetime | None
    expires_at: dt.datetime | None
    links: dict[str, str]


class CaptureOut(CaptureItem):
    files: CaptureFilesOut
    error: ErrorInfo | None = Field(description="Why the last commit failed (state uploading).")


class CapturePage(BaseModel):
    items: list[CaptureItem]
    next_cursor: str | None


class FileOut(BaseModel):
    path: str
    size: int
    sha256: str
    state: FileState


class FilePage(BaseModel):
    items: list[FileOut]
    next_cursor: str | None


# -- jobs ----------------------------------------------------------------------------------------
class JobIn(_In):
    capture_id: str = Field(min_length=1, max_length=64)
    pipeline: str = Field(DEFAULT_PIPELINE, min_length=1, max_length=32,
                          description="A pipeline of GET /v1/pipelines.")
    params: Annotated[dict[str, Any], WithJsonSchema(schema(ReconstructParams, inline=True))] = \
        Field(default_factory=dict, description=(
            "The pipeline's parameters, checked before the job is made (422 naming each bad "
            "one); the reconstruct pipeline's are described here, every pipeline's in GET "
            "/v1/pipelines."))
    name: Name = ""
    expires_at: AwareDatetime | None = None


class ProgressOut(BaseModel):
    stage: str
    frame: int
    frames: int
    iteration: int
    iterations: int
    fraction: float = Field(description="0..1; never decreases, also across a resume.")
    eta_s: float | None
    message: str


class RunOut(BaseModel):
    """One run of a job or part: a worker's claim of it, and how it ended."""

    attempt: int = Field(description="The attempt it was (1, 2, ...; counted again after a "
                                     "retry).")
    worker: str = Field(description="host/pid of the worker process.")
    started_at: dt.datetime
    ended_at: dt.datetime | None = Field(None, description="null while it runs.")
    outcome: Literal["succeeded", "failed", "cancelled", "released", "lost"] | None = Field(
        None, description="released: its worker shut down and gave it back; lost: its worker "
                          "stopped renewing its lease (killed, or its machine gone).")


WORKER = "host/pid of the worker that runs it, or ran it last (kept after it ends)."
ATTEMPTS = ("How many times a worker took it, every run counted (retries too): the number of "
            "its latest run in `runs`.")
RUNS = "Each worker that took it, oldest first (at most the last 20)."


class PartOut(BaseModel):
    """One part of a sequence job run as parts (one group of pictures, docs/design.md 4.4)."""

    index: int = Field(description="The group of pictures (0-based).")
    frames: list[str] = Field(description="Its frames in order; the first is its key frame.")
    state: JobState
    worker: str | None = Field(description=WORKER)
    runs: list[RunOut] = Field(description=RUNS)
    attempts: int = Field(description=ATTEMPTS)
    stage: str
    frame: int = Field(description="Its frame being made (1-based, within the part).")
    iteration: int
    iterations: int
    fraction: float = Field(description="0..1 of the part; never decreases.")
    eta_s: float | None
    started_at: dt.datetime | None
    finished_at: dt.datetime | None
    error: ErrorInfo | None


class JobOut(BaseModel):
    id: str
    name: str
    capture_id: str | None
    source_job_id: str | None = Field(description=(
        "The reconstruction a relight job renders (null for other jobs, or once deleted)."))
    pipeline: str
    params: dict[str, Any]
    state: JobState
    progress: ProgressOut
    error: ErrorInfo | None
    attempts: int = Field(description=ATTEMPTS)
    worker: str | None = Field(None, description=WORKER + " A job run as parts: null (see "
                                                          "its parts').")
    runs: list[RunOut] = Field(default_factory=list, description=RUNS)
    cancel_requested: bool
    created_at: dt.datetime
    updated_at: dt.datetime
    started_at: dt.datetime | None
    finished_at: dt.datetime | None
    expires_at: dt.datetime | None
    parts: list[PartOut] | None = Field(None, description=(
        "A sequence reconstruction of several groups of pictures runs as parts, one per group, "
        "on any idle workers; then progress is over all of them (the ETA from their measured "
        "rates) and this lists each. null for a job that runs as one."))
    links: dict[str, str]


class JobPage(BaseModel):
    items: list[JobOut]
    next_cursor: str | None


class LogsOut(BaseModel):
    lines: list[str]
    offset: int
    next_offset: int = Field(description="Pass as offset to read on.")
    complete: bool = Field(description="The job has ended and no line follows next_offset.")


# -- artifacts and assets ------------------------------------------------------------------------
class ArtifactOut(BaseModel):
    path: str
    kind: str
    frame: str | None
    size: int
    sha256: str
    content_type: str
    created_at: dt.datetime
    url: str


class ArtifactPage(BaseModel):
    items: list[ArtifactOut]
    next_cursor: str | None


class AssetOut(BaseModel):
    id: str
    kind: str
    filename: str
    size: int
    sha256: str
    content_type: str
    width: int
    height: int
    channels: int
    sh9: list[list[float]] | None = Field(None, description=(
        "An environment map's 9-coefficient SH radiance (9 x RGB) in its own frame (poles on "
        "+z, unrotated), for relighting in the browser; null for maps stored before it."))
    created_at: dt.datetime
    expires_at: dt.datetime | None
    links: dict[str, str]


class AssetPage(BaseModel):
    items: list[AssetOut]
    next_cursor: str | None


class LightIn(Light):
    """A light: directional (`direction` towards it) or point (`position`), intensity > 0."""


class RenderIn(RelightJobParams):
    """A reconstruction (job_id) and the relight pipeline's parameters to render it with."""

    job_id: str = Field(min_length=1, max_length=64, description=(
        "A succeeded reconstruct job of yours; it cannot be deleted while this render is "
        "queued or running."))
    lights: Annotated[tuple[LightIn, ...], AsTuple] = Field(
        (), max_length=64, description="Lights added to the map.")
    name: Name = ""
    expires_at: AwareDatetime | None = None

    def params(self) -> dict[str, Any]:
        """The relight job's stored parameters."""
        return RelightJobParams.model_validate(self.model_dump(
            exclude={"job_id", "name", "expires_at"})).model_dump(mode="json")


class ExportIn(ExportJobParams):
    """A reconstruction (job_id) and the export pipeline's parameters to deliver it with."""

    job_id: str = Field(min_length=1, max_length=64, description=(
        "A succeeded reconstruct job of yours; it cannot be deleted while this export is "
        "queued or running."))
    name: Name = ""
    expires_at: AwareDatetime | None = None

    def params(self) -> dict[str, Any]:
        """The export job's stored parameters."""
        return ExportJobParams.model_validate(self.model_dump(
            exclude={"job_id", "name", "expires_at"})).model_dump(mode="json")
