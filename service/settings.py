"""The API process's settings: the worker's (where state lives, DGS_* variables) plus where it
listens and the limits it enforces on what clients send. Limits are published in /v1/info."""

from __future__ import annotations

import functools
from urllib.parse import urlsplit

from pydantic import Field, field_validator

from core.data.rules import MAX_METADATA_BYTES
from worker.settings import WorkerSettings

__all__ = ["ServiceSettings", "get_service_settings"]

GiB = 1 << 30
MiB = 1 << 20


class ServiceSettings(WorkerSettings):
    """One object per API process (`create_app(settings)`); environment DGS_<FIELD>."""

    host: str = "127.0.0.1"
    """Interface `dgs serve` binds to. Anything but loopback needs at least one API key."""
    port: int = Field(8000, ge=0, le=65535)
    """TCP port of `dgs serve`."""
    public_url: str | None = None
    """Base URL clients reach the service at (https://dgs.example.com behind a proxy); used
    for absolute Location headers and links. None: links are relative to the request's host."""
    cors_origins: list[str] = Field(default_factory=list)
    """Web origins allowed to call the API from a browser (tus-js-client, Uppy on another
    site), e.g. ["https://studio.example.com"]; DGS_CORS_ORIGINS='["..."]'. Empty: none."""
    max_file_bytes: int = Field(64 * GiB, ge=1)
    """Largest single file of a capture (a declared size above it is refused at creation)."""
    max_capture_bytes: int = Field(2 * 1024 * GiB, ge=1)
    """Largest capture: the sum of its manifest's sizes (and of an archive's members)."""
    max_capture_files: int = Field(1_000_000, ge=1)
    """Most files in one capture manifest."""
    max_path_bytes: int = Field(1024, ge=16, le=1024)
    """Longest manifest path (UTF-8 bytes; the uploads table holds 1024)."""
    max_archive_bytes: int = Field(4 * GiB, ge=1)
    """Largest body of the one-request zip upload (POST /v1/captures/archive); larger captures
    use the resumable uploads."""
    max_archive_expanded_bytes: int = Field(16 * GiB, ge=1)
    """Most bytes one archive may expand to (the sum of its members' sizes)."""
    max_archive_members: int = Field(100_000, ge=1)
    """Most members in one zip archive."""
    max_archive_ratio: float = Field(200.0, gt=1)
    """Largest uncompressed/compressed size ratio of an archive member (zip bombs); images
    and calibration text stay far below it."""
    max_asset_bytes: int = Field(1 * GiB, ge=1)
    """Largest environment map (POST /v1/assets)."""
    max_json_bytes: int = Field(1 * MiB, ge=1024)
    """Largest JSON request body but a manifest's (a job, render or export request is a few
    kB; files go up with tus uploads or a zip archive, under their own limits)."""
    max_manifest_bytes: int = Field(256 * MiB, ge=1024)
    """Largest body of a capture manifest (POST /v1/captures, PATCH .../manifest): one of a
    million files is about 150 MiB."""
    max_json_file_bytes: int = Field(MAX_METADATA_BYTES, ge=1024, le=MAX_METADATA_BYTES)
    """Largest .json file in a capture manifest (parsed whole, in memory, at commit): at most
    core's limit on a metadata file (core.data.rules.MAX_METADATA_BYTES, 64 MiB), which the
    commit applies anyway, so a larger file is refused when it is declared."""
    commit_wait_seconds: float = Field(20.0, ge=0)
    """How long POST /v1/captures/{id}/commit waits for validation before it answers 202
    (state committing) and finishes in the background."""
    sse_poll_seconds: float = Field(0.5, gt=0)
    """How often an event stream polls the job store for new events."""
    sse_keepalive_seconds: float = Field(15.0, gt=0)
    """Interval of the keep-alive comment on an idle event stream (proxies drop silent ones)."""
    idempotency_key_hours: float = Field(24.0, gt=0, le=24 * 30)
    """How long a submit's Idempotency-Key answers the job it made (POST /v1/jobs, /v1/renders,
    /v1/exports); after that the key may make a new job."""
    max_active_jobs: int = Field(50, ge=1)
    """Most jobs one tenant may have queued or running at once (a job run as parts counts
    once; renders and exports count): a submit or retry past it answers 429 too_many_jobs.
    It bounds one tenant's share of the queue."""
    max_event_streams: int = Field(20, ge=1)
    """Most event streams (GET /v1/jobs/{id}/events) one tenant may hold open at once on one
    API process; one more answers 429 too_many_streams. Each open stream polls the job store."""
    event_streams_per_minute: float = Field(60.0, gt=0)
    """Event streams one tenant may open a minute on one API process, once it has opened
    `max_event_streams` at once; past it, 429 too_many_streams with Retry-After. The cap on
    open streams bounds how many poll at once, this how fast a client may open and drop
    them (each opening reads the job store)."""
    job_changes_per_minute: float = Field(60.0, gt=0)
    """Job state changes (submits of jobs, renders and exports; cancel; retry; delete) one
    tenant may make a minute on average, across every API process (the buckets live in the
    job store); past it, 429 rate_limited with Retry-After. A request refused for another
    reason (404, 409, 422) or an idempotent replay changes nothing and counts nothing."""
    job_changes_burst: int = Field(20, ge=1)
    """How many job state changes one tenant may make at once before the rate applies."""
    upload_sync_bytes: int = Field(64 * MiB, ge=MiB)
    """A long tus PATCH makes its progress durable (fsync, then the offset in the job store)
    every this many bytes, so a crash of the API process loses at most this much."""

    @field_validator("public_url")
    @classmethod
    def _public_url(cls, value: str | None) -> str | None:
        # Without a scheme the base would make relative Location headers and links.
        parts = urlsplit(value) if value is not None else None
        if parts is not None and (parts.scheme not in ("http", "https") or not parts.netloc):
            raise ValueError(f"expected the base URL clients reach the service at, such as "
                             f"https://dgs.example.com; got {value[:200]!r}")
        return value


@functools.lru_cache(maxsize=1)
def get_service_settings() -> ServiceSettings:
    """The process's settings, read once from the environment (for entry points)."""
    return ServiceSettings()
