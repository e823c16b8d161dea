"""The job store's tables (SQLAlchemy 2 declarative). Migrations: worker/migrations (Alembic).

Every capture, upload, job and asset belongs to one tenant; API keys name their tenant. Times
are timezone-aware UTC (stored naive on SQLite, given back with tzinfo=UTC).
"""

from __future__ import annotations

import datetime as dt
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

__all__ = [
    "ApiKey",
    "Artifact",
    "Asset",
    "Base",
    "Capture",
    "IdempotencyKey",
    "Job",
    "JobEvent",
    "JobLog",
    "RateBucket",
    "Upload",
    "utcnow",
]


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


class UTCDateTime(TypeDecorator):
    """Aware UTC datetimes on every backend (SQLite keeps no zone)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: dt.datetime | None, dialect) -> dt.datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime given to the job store; use worker.models.utcnow()")
        value = value.astimezone(dt.UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: dt.datetime | None, dialect) -> dt.datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=dt.UTC) if value.tzinfo is None else value.astimezone(dt.UTC)


# Stable constraint names, so migrations are the same on SQLite and PostgreSQL.
NAMING = {"ix": "ix_%(column_0_label)s", "uq": "uq_%(table_name)s_%(column_0_name)s",
          "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
          "pk": "pk_%(table_name)s"}


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING)
    type_annotation_map = {dt.datetime: UTCDateTime(), dict[str, Any]: JSON, list[Any]: JSON}


class ApiKey(Base):
    """A bearer key. Only a SHA-256 of its secret part is stored (the key is 256 random bits,
    so a fast hash is enough); the id is the public part, shown in listings."""

    __tablename__ = "api_keys"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    tenant: Mapped[str] = mapped_column(String(64), index=True)
    name: Mapped[str] = mapped_column(String(128), default="")
    secret_sha256: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    revoked_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    last_used_at: Mapped[dt.datetime | None] = mapped_column(default=None)


class Capture(Base):
    """An uploaded capture: its manifest while uploading, then frozen once committed."""

    __tablename__ = "captures"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    tenant: Mapped[str] = mapped_column(String(64), index=True)
    name: Mapped[str] = mapped_column(String(256), default="")
    format: Mapped[str] = mapped_column(String(32))
    state: Mapped[str] = mapped_column(String(16), index=True)
    """uploading | committing | ready | failed"""
    manifest: Mapped[list[Any]] = mapped_column(default=list)
    """[{"path", "size", "sha256"}] as declared at creation."""
    total_bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    summary: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    """After commit: frames, cameras, image size, masks, normals."""
    error: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    """The last failed commit's problems (the capture stays uploading)."""
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[dt.datetime] = mapped_column(default=utcnow, onupdate=utcnow)
    committed_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    expires_at: Mapped[dt.datetime | None] = mapped_column(default=None, index=True)


class Upload(Base):
    """One tus upload of one manifest file."""

    __tablename__ = "uploads"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    tenant: Mapped[str] = mapped_column(String(64), index=True)
    capture_id: Mapped[str] = mapped_column(ForeignKey("captures.id", ondelete="CASCADE"),
                                            index=True)
    path: Mapped[str] = mapped_column(String(1024))
    length: Mapped[int] = mapped_column(BigInteger)
    offset: Mapped[int] = mapped_column(BigInteger, default=0)
    state: Mapped[str] = mapped_column(String(16))
    """receiving | received | duplicate | corrupt | terminated"""
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[dt.datetime] = mapped_column(default=utcnow, onupdate=utcnow)


class Job(Base):
    """A pipeline run on a capture (a relight job: on a reconstruction's results), with its
    progress, lease and outcome."""

    __tablename__ = "jobs"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    tenant: Mapped[str] = mapped_column(String(64), index=True)
    capture_id: Mapped[str | None] = mapped_column(
        ForeignKey("captures.id", ondelete="SET NULL"), index=True, default=None)
    pipeline: Mapped[str] = mapped_column(String(32))
    params: Mapped[dict[str, Any]] = mapped_column(default=dict)
    """The parameters as the request gave them (what the API shows)."""
    resolved_run: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    """A reconstruction's run, resolved at submit against its capture (RUN/config.json's
    content, `core.config.ResolvedRun`), which the worker runs as it is (migration 0007);
    None for other pipelines and for jobs stored before it existed."""
    source_job_id: Mapped[str | None] = mapped_column(String(32), index=True, default=None)
    """The reconstruction a relight job renders; None for other jobs, and once the source is
    deleted. Not a foreign key (see migration 0002): deleting a job is refused while a queued
    or running job needs it, and clears this field of the finished ones."""
    name: Mapped[str] = mapped_column(String(256), default="")
    parent_id: Mapped[str | None] = mapped_column(String(32), index=True, default=None)
    """A part (one group of pictures of a sequence job, docs/design.md 4.4): the sequence job
    it belongs to; None for every other job. Not a foreign key (see migration 0003)."""
    part_index: Mapped[int | None] = mapped_column(Integer, default=None)
    """A part's group of pictures (0-based), the order of the parent's parts."""
    part_frames: Mapped[list[Any] | None] = mapped_column(default=None)
    """A part's frames, in order (the first is its key frame)."""
    parts: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    """A sequence job run as parts: how many (0: the job runs as one)."""
    state: Mapped[str] = mapped_column(String(16), index=True)
    """queued | running | succeeded | failed | cancelled"""
    stage: Mapped[str] = mapped_column(String(64), default="queued")
    frame: Mapped[int] = mapped_column(Integer, default=0)
    frames: Mapped[int] = mapped_column(Integer, default=0)
    iteration: Mapped[int] = mapped_column(Integer, default=0)
    iterations: Mapped[int] = mapped_column(Integer, default=0)
    fraction: Mapped[float] = mapped_column(Float, default=0.0)
    """0..1, never decreases (a resumed job holds it until it passes its old value)."""
    eta_s: Mapped[float | None] = mapped_column(Float, default=None)
    message: Mapped[str] = mapped_column(String(512), default="")
    error: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    """{"code", "message", "retryable"} when failed."""
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    """Times a worker claimed the job, retries included: the number of its latest run."""
    redeliveries: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    """Claims since the job was last queued by a retry, less those given back by a worker
    shutting down: what the redelivery cap (DGS_MAX_ATTEMPTS) counts (migration 0008)."""
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    lease_owner: Mapped[str | None] = mapped_column(String(256), default=None)
    worker: Mapped[str | None] = mapped_column(String(256), default=None)
    """host/pid of the worker that runs it or ran it last (kept when the lease ends)."""
    runs: Mapped[list[Any] | None] = mapped_column(default=None)
    """Each claim, newest last (at most worker.lease.MAX_RUNS): {"attempt", "worker",
    "started_at", "ended_at", "outcome"}; a run its worker never ended is "lost"."""
    lease_expires_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    dispatched_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    dispatches: Mapped[int] = mapped_column(Integer, default=0)
    run_started_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    run_start_fraction: Mapped[float] = mapped_column(Float, default=0.0)
    picked_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    """When a free worker's fair pick (`worker.fair`) last gave it a worker; None if never
    (migration 0009)."""
    yield_asked_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    """When the fair share (`worker.fair`) asked its running job to give its worker up at the
    next step; cleared by the next claim (migration 0010)."""
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[dt.datetime] = mapped_column(default=utcnow, onupdate=utcnow)
    started_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    finished_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    expires_at: Mapped[dt.datetime | None] = mapped_column(default=None, index=True)

    __table_args__ = (Index("ix_jobs_tenant_created", "tenant", "created_at", "id"),
                      Index("ix_jobs_tenant_picked", "tenant", "picked_at"))


class JobEvent(Base):
    """Progress and state changes in order; the id is the SSE event id (Last-Event-ID)."""

    __tablename__ = "job_events"
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"),
                                    primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(16))
    """state | progress | artifact"""
    data: Mapped[dict[str, Any]] = mapped_column(default=dict)
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)


class JobLog(Base):
    """The job's log, one row per line; `seq` (0, 1, ...) is the offset clients page with."""

    __tablename__ = "job_logs"
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"),
                                    primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"))
    seq: Mapped[int] = mapped_column(Integer)
    line: Mapped[str] = mapped_column(Text)
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)

    __table_args__ = (UniqueConstraint("job_id", "seq", name="uq_job_logs_job_seq"),)


class Artifact(Base):
    """A file a job produced, in the artifact store under jobs/<job>/artifacts/<path>."""

    __tablename__ = "artifacts"
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"),
                                    primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    path: Mapped[str] = mapped_column(String(1024))
    kind: Mapped[str] = mapped_column(String(32))
    frame: Mapped[str | None] = mapped_column(String(64), default=None)
    size: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(String(64))
    content_type: Mapped[str] = mapped_column(String(128))
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)

    __table_args__ = (UniqueConstraint("job_id", "path", name="uq_artifacts_job_path"),)


class Asset(Base):
    """An uploaded input that is not a capture (environment maps)."""

    __tablename__ = "assets"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    tenant: Mapped[str] = mapped_column(String(64), index=True)
    kind: Mapped[str] = mapped_column(String(32))
    filename: Mapped[str] = mapped_column(String(256))
    size: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(String(64))
    content_type: Mapped[str] = mapped_column(String(128))
    meta: Mapped[dict[str, Any]] = mapped_column(default=dict)
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[dt.datetime | None] = mapped_column(default=None, index=True)


class IdempotencyKey(Base):
    """A client's Idempotency-Key of a submit (POST /v1/jobs, /v1/renders, /v1/exports) and the
    job it made. Unique per tenant: two submits racing with one key make one job, because the
    second insert fails on this constraint in the transaction that would add its job (never a
    check, then an insert). Deleted with its job (cascade) or once expired (the sweeper)."""

    __tablename__ = "idempotency_keys"
    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"),
                                    primary_key=True, autoincrement=True)
    tenant: Mapped[str] = mapped_column(String(64))
    key: Mapped[str] = mapped_column(String(255))
    request_sha256: Mapped[str] = mapped_column(String(64))
    """What was asked (the operation and its validated body): a key reused for another
    request is refused."""
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[dt.datetime] = mapped_column(index=True)

    __table_args__ = (UniqueConstraint("tenant", "key", name="uq_idempotency_keys_tenant_key"),)


class RateBucket(Base):
    """A token bucket of the API's rate limits (`worker.quota`), shared by every API process
    through the job store: `tokens` left at `stamp` (seconds since the epoch), refilled at the
    limit's rate. One row per tenant and limit, e.g. "changes:<tenant>"."""

    __tablename__ = "rate_buckets"
    key: Mapped[str] = mapped_column(String(128), primary_key=True)
    tokens: Mapped[float] = mapped_column(Float)
    stamp: Mapped[float] = mapped_column(Float)
