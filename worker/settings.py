"""Settings shared by the API and the workers: one object per process, from DGS_* variables.

The embedded default needs nothing set: a data folder holds the SQLite job store, the SQLite
broker (Kombu's SQLAlchemy transport) and the local artifact store. A deployment sets
DGS_DATABASE_URL (PostgreSQL), DGS_BROKER_URL (Redis) and DGS_STORAGE_URL (s3://bucket/prefix)
and the same code runs distributed (docs/design.md section 4).
"""

from __future__ import annotations

import functools
import json
import os
import re
from pathlib import Path

from pydantic import Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from core.config import DEVICE_PATTERN
from core.data.headers import DEFAULT_MAX_PIXELS

# A model the operator offers by name (not an asset id, which starts with "ast_").
MODEL_NAME = r"^(?!ast_)[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$"

__all__ = ["WorkerSettings", "describe", "get_settings"]


DATABASES = ("sqlite", "postgresql")
"""The job store's backends (SQLAlchemy dialect names)."""


def _backend(url: str) -> str:
    """The SQLAlchemy backend of `url` ("postgresql" for postgresql+psycopg://...)."""
    scheme = url.split("://", 1)[0] if "://" in url else ""
    if url.startswith("sqlite:") and not url.startswith("sqlite://"):
        return ""
    return scheme.split("+", 1)[0].lower()


def _scheme_of(url: str) -> str:
    """What an error shows of a URL: its scheme only (the rest may hold a password)."""
    return f"scheme {url.split('://', 1)[0][:40]!r}" if "://" in url else "no scheme (no '://')"


def _default_data_dir() -> Path:
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "dgs"


class WorkerSettings(BaseSettings):
    """Where state lives and how jobs run. Environment variables: DGS_<FIELD> (upper case)."""

    # Empty variables count as unset (docker-compose passes `DGS_RETENTION_DAYS=` through).
    model_config = SettingsConfigDict(env_prefix="DGS_", extra="ignore", env_ignore_empty=True)

    data_dir: Path = Field(default_factory=_default_data_dir)
    """Folder of the embedded default: job store, broker, uploads, artifacts, worker scratch."""
    database_url: str | None = None
    """SQLAlchemy URL of the job store (postgresql+psycopg://... in deployment); default
    sqlite:///<data_dir>/dgs.sqlite3."""
    broker_url: str | None = None
    """Celery broker (redis://... in deployment); default the Kombu SQLAlchemy transport on
    <data_dir>/broker.sqlite3, and `dgs serve` then supervises an embedded worker."""
    storage_url: str | None = None
    """Artifact store: s3://bucket/prefix for S3-compatible storage, default the local folder
    <data_dir>/store."""
    s3_endpoint_url: str | None = None
    """Endpoint of an S3-compatible store (MinIO, Ceph, ...); None: AWS. Credentials come from
    the standard AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY variables."""
    s3_region: str | None = None
    """Region name passed to boto3 (some S3-compatible stores want one)."""
    queue: str = "dgs"
    """Celery queue the jobs go to (one per deployment; tests use their own)."""
    worker_name: str | None = None
    """Celery node name suffix of `dgs worker` (dgs-<name>@<host>); one per GPU on a machine."""
    redis_key_prefix: str = ""
    """Prefix of every Redis key the broker uses (several deployments on one Redis)."""
    scratch_dir: Path | None = None
    """Worker working folder (captures fetched from S3, run directories); default
    <data_dir>/work. With local storage it must be on the machine that holds data_dir."""
    lease_seconds: float = Field(60.0, gt=0)
    """A running job's lease: a worker that stops renewing it for this long is considered
    dead and the job is handed to another worker (resuming from its checkpoint)."""
    heartbeat_seconds: float = Field(1.0, gt=0)
    """How often a worker writes progress, logs and its lease renewal to the job store."""
    watch_seconds: float = Field(0.2, gt=0)
    """How often a running job looks (a read) for a cancel or another tenant's turn between
    its heartbeats: a worker is freed for them within this, not within a heartbeat."""
    stall_seconds: float = Field(300.0, gt=0)
    """A pool process that runs a task but has held no live lease for this long (stuck
    before its claim, or after its job ended) is killed by its worker's watchdog, as is one
    whose lease lapsed (worker.watchdog); its job goes back to the queue."""
    max_attempts: int = Field(3, ge=1)
    """Redelivery cap: a job whose worker was lost this many times fails (retryable)."""
    cancel_grace_seconds: float = Field(5.0, gt=0)
    """After a cancel, how long a worker waits for the job to stop between two steps before it
    ends its own process."""
    share_after_seconds: float = Field(1.0, ge=0)
    """Fair share of the workers (worker.fair): a job of a tenant holding at least two workers
    more than a tenant with a waiting job gives its worker up at its next step (a checkpoint,
    back in the queue, no attempt counted) once it has held it this long; 0 never. The wait
    keeps every claim making progress."""
    time_slice_seconds: float = Field(0.0, ge=0)
    """Time slicing (worker.fair), for fewer workers than tenants: a job of a tenant holding
    more workers than one with a waiting job gives its worker up after holding it this long.
    0 (the default): never; a job then runs to its end and the next turn goes to the waiting
    tenant. Each slice costs the job a checkpoint and a process start."""
    lost_message_seconds: float = Field(120.0, gt=0)
    """How often the sweepers look into the broker (Redis or the embedded one) for queued jobs
    whose message is gone (lost with a worker that died holding it, or with Redis's data), and
    send those again. A message delivered to a worker this long ago (and at least a lease ago)
    whose job is still queued counts as gone too. Jobs that merely wait behind others are never
    sent twice."""
    capture_cache_seconds: float = Field(24 * 3600.0, gt=0)
    """A capture a worker fetched from S3 into its scratch space is deleted once no job holds
    it, no active job needs it and nobody used it for this long (at once if the capture was
    deleted); checked with the lost messages (`lost_message_seconds`)."""
    requeue_after_seconds: float = Field(6 * 3600.0, gt=0)
    """Only for a broker the sweepers cannot look into (neither Redis nor the embedded one): a
    queued job last sent this long ago is sent again."""
    reconstruct_soft_limit_seconds: float = Field(48 * 3600.0, gt=0)
    """Soft time limit of a reconstruction job (it fails cleanly, checkpoint kept)."""
    relight_soft_limit_seconds: float = Field(2 * 3600.0, gt=0)
    """Soft time limit of a relight (render) job: views of frames already reconstructed, so
    far shorter than a reconstruction; a long sequence's orbit may want more."""
    export_soft_limit_seconds: float = Field(2 * 3600.0, gt=0)
    """Soft time limit of an export job (PLY, SPZ, the sequence stream of a finished
    reconstruction): the stream's graph fit and encoding grow with the frames and Gaussians."""
    hard_limit_margin_seconds: float = Field(600.0, gt=0)
    """The hard limit (process killed) is the soft limit plus this margin."""
    max_image_pixels: int = Field(DEFAULT_MAX_PIXELS, ge=1)
    """Largest image (width x height) the API and the workers decode: capture images, masks,
    normal maps and environment maps. Checked from the file's header before any decoding, so
    a 20000 x 20000 PNG is refused in microseconds (the default passes a 16384 x 8192 map)."""
    pool_tasks_per_process: int = Field(100, ge=1)
    """Tasks a worker's pool process runs before Celery replaces it with a fresh one. A process
    kept between jobs starts the next at once (an interpreter and torch take seconds, which a
    waiting tenant's job would otherwise wait; issue 42); 1 starts every job fresh."""
    pool_process_max_mib: int | None = Field(4096, ge=64)
    """A pool process whose peak resident memory reached this (MiB) is replaced after its task,
    so a large job's heap never carries into the next one; None: no limit."""
    torch_threads: int | None = Field(None, ge=1, le=1024)
    """Threads a job's training uses (torch.set_num_threads); None leaves torch's default (every
    core). `dgs serve --workers N` gives each embedded worker the machine's cores divided by N,
    so N workers do not oversubscribe the cores."""
    retention_days: float | None = None
    """Default lifetime of captures, jobs and assets (expires_at); None keeps them until
    deleted. Expiry is shown on every object and logged when it happens."""
    devices: str = "auto,cpu"
    """The devices a job may ask for (`train.device`, `mesh.device`), comma separated: a GPU
    deployment adds cuda and cuda:0 (cuda:1, ... on a worker with several GPUs)."""
    normal_estimators: dict[str, Path] = Field(default_factory=dict)
    """Normal-prior models the operator offers to every tenant, by name (JSON:
    DGS_NORMAL_ESTIMATORS='{"omnidata": "/models/omnidata_normal.pt"}'); a job names one as
    `normal_estimator`, or names a model asset of its own tenant. A path is never taken from a
    request."""

    @field_validator("database_url")
    @classmethod
    def _database_url(cls, value: str | None) -> str | None:
        if value is not None and _backend(value) not in DATABASES:
            raise ValueError(f"expected a job store URL sqlite:///path or "
                             f"postgresql+psycopg://user@host/db; got {_scheme_of(value)}")
        return value

    @field_validator("broker_url")
    @classmethod
    def _broker_url(cls, value: str | None) -> str | None:
        if value is None:
            return value
        scheme = value.split("://", 1)[0].lower() if "://" in value else ""
        inner = scheme.split("+", 1)[1] if scheme.startswith("sqla+") else None
        if scheme not in ("redis", "rediss") and (inner is None or _backend(
                value[len("sqla+"):]) not in DATABASES):
            raise ValueError(f"expected a broker URL redis://host:6379/0, rediss://... or "
                             f"sqla+sqlite:///path; got {_scheme_of(value)}")
        return value

    @field_validator("storage_url")
    @classmethod
    def _storage_url(cls, value: str | None) -> str | None:
        if value is None:
            return value
        scheme, _, rest = value.partition("://")
        if scheme.lower() not in ("file", "s3") or not rest.strip("/"):
            raise ValueError(f"expected an artifact store URL s3://bucket/prefix or "
                             f"file:///folder; got {_scheme_of(value)}")
        return value

    @field_validator("devices")
    @classmethod
    def _devices(cls, value: str) -> str:
        names = [d.strip() for d in value.split(",") if d.strip()]
        bad = [d for d in names if not re.match(DEVICE_PATTERN, d)]
        if not names or bad:
            raise ValueError(f"expected devices such as auto,cpu,cuda,cuda:0; got {value!r}")
        return ",".join(names)

    @field_validator("normal_estimators")
    @classmethod
    def _model_names(cls, value: dict[str, Path]) -> dict[str, Path]:
        bad = [n for n in value if not re.match(MODEL_NAME, n)]
        if bad:
            raise ValueError(f"model names: letters, digits, '_', '-' and '.', not starting "
                             f"like an asset id (ast_...); got {bad}")
        return {n: p.expanduser().resolve() for n, p in value.items()}

    def to_env(self) -> dict[str, str]:
        """DGS_* variables that give a subprocess (an embedded worker) these settings."""
        env = {}
        for name, value in self.model_dump(mode="json").items():
            if name in WorkerSettings.model_fields and value is not None:
                env[f"DGS_{name.upper()}"] = (json.dumps(value) if isinstance(value, (dict, list))
                                              else str(value))
        return env

    @property
    def offered_devices(self) -> list[str]:
        """`devices` as a list."""
        return self.devices.split(",")

    @field_validator("data_dir", "scratch_dir", mode="after")
    @classmethod
    def _absolute(cls, value: Path | None) -> Path | None:
        return None if value is None else value.expanduser().resolve()

    @property
    def database(self) -> str:
        """The job store URL, defaults applied."""
        return self.database_url or f"sqlite:///{self.data_dir / 'dgs.sqlite3'}"

    @property
    def broker(self) -> str:
        """The broker URL, defaults applied."""
        return self.broker_url or f"sqla+sqlite:///{self.data_dir / 'broker.sqlite3'}"

    @property
    def embedded_broker(self) -> bool:
        """True when no broker is configured (the SQLite transport of the embedded default)."""
        return self.broker_url is None

    @property
    def storage(self) -> str:
        """The artifact store URL, defaults applied (file:// or s3://)."""
        return self.storage_url or (self.data_dir / "store").as_uri()

    @property
    def scratch(self) -> Path:
        return self.scratch_dir or self.data_dir / "work"

    @property
    def visibility_timeout(self) -> float:
        """Redis visibility timeout: longer than the longest hard limit (docs/design.md section 4),
        so a long job's message is never handed to a second worker while the first runs."""
        longest = max(self.reconstruct_soft_limit_seconds, self.relight_soft_limit_seconds,
                      self.export_soft_limit_seconds)
        return 2 * (longest + self.hard_limit_margin_seconds)


@functools.lru_cache(maxsize=1)
def get_settings() -> WorkerSettings:
    """The process's settings (read once from the environment)."""
    return WorkerSettings()


def describe(exc: ValidationError) -> str:
    """Settings refused, as the operator set them: `DGS_BROKER_URL: expected ...; ...`."""
    return "; ".join(f"DGS_{'_'.join(map(str, e['loc'])).upper()}: "
                     f"{e['msg'].removeprefix('Value error, ')}" for e in exc.errors())
