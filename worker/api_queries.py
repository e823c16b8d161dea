"""What the API asks of the job store besides a job's lifecycle: a tenant's capture, upload or
asset by id, pages of jobs, captures, assets and artifacts (keyset cursors), deleting them,
amending an uploading capture's manifest, undoing a dispatch the broker refused, a tenant's
jobs per state. `worker.store.JobStore` inherits it, so the API's queries live in the store,
never in a router (issue 40; `tests/test_layering.py` keeps SQLAlchemy out of the routers).

Outcomes are typed (rows, `Deleted`); `service.lookups` turns them into HTTP answers.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

from sqlalchemy import Select, and_, delete, func, or_, select, text, update
from sqlalchemy.orm import Session, defer

from worker.models import Artifact, Asset, Capture, Job, Upload
from worker.parts import delete_parts
from worker.transitions import ACTIVE

__all__ = ["ApiQueries", "Deleted", "Key", "assets_named", "newest_page"]

Key = tuple[dt.datetime, str]
"""Where a page ends: the (created_at, id) of its last row."""


def newest_page(s: Session, query: Select, created_col, id_col, after: Key | None,
                limit: int) -> tuple[list, Key | None]:
    """One page of `query`'s rows, newest first by (created_at, id) strictly after `after`,
    and the key of its last row when another page follows (None on the last). Rows inserted
    meanwhile never shift a page, and every row is listed once."""
    if after is not None:
        created, ident = after
        query = query.where(or_(created_col < created,
                                and_(created_col == created, id_col < ident)))
    rows = list(s.scalars(query.order_by(created_col.desc(), id_col.desc()).limit(limit + 1)))
    if len(rows) <= limit:
        return rows, None
    rows = rows[:limit]
    return rows, (rows[-1].created_at, rows[-1].id)


def assets_named(params: dict[str, Any] | None) -> set[str]:
    """The asset ids a job's parameters name: a render's envmap, a reconstruction's normal
    estimator (a built-in map's or a server model's name is no asset's id, and harmless)."""
    params = params or {}
    named = {params.get("envmap"), (params.get("config") or {}).get("normal_estimator")}
    return {n for n in named if isinstance(n, str)}


@dataclass(frozen=True)
class Deleted:
    """What deleting a job or a capture did."""

    status: Literal["deleted", "missing", "refused"]
    """deleted; missing (none of the tenant's); refused (`why`)."""
    why: str = ""
    """Why it was refused, and what to do: the job is queued or running, a queued or running
    job needs its results or uses the capture or the asset, or the capture is being
    validated."""
    retryable: bool = False
    """The refusal ends by itself (a capture being validated)."""
    ids: list[str] = field(default_factory=list)
    """What was deleted: a job's id and its parts' (whose files the caller deletes), the
    capture's or the asset's id."""


class ApiQueries:
    """The job store's queries for the API (module docstring)."""

    def ping(self) -> None:
        """One round trip to the database (readiness); what the driver raises, when not."""
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            s.execute(text("SELECT 1"))

    # -- jobs -------------------------------------------------------------------------------
    @staticmethod
    def dependents(s: Session, job_id: str) -> list[str]:
        """Queued or running jobs that need `job_id`'s results (in session `s`)."""
        return list(s.scalars(select(Job.id).where(Job.source_job_id == job_id,
                                                   Job.state.in_(ACTIVE))))

    def job_page(self, tenant: str, state: str | None, after: Key | None,
                 limit: int) -> tuple[list[Job], Key | None]:
        """The tenant's jobs (not their parts), newest first (`newest_page`)."""
        q = select(Job).where(Job.tenant == tenant, Job.parent_id.is_(None))
        if state is not None:
            q = q.where(Job.state == state)
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            return newest_page(s, q, Job.created_at, Job.id, after, limit)

    def undispatch(self, job_id: str) -> None:
        """The broker refused the job's message: it counts as never sent, so a sweeper sends
        it."""
        with self.session() as s:  # type: ignore[attr-defined]
            s.execute(update(Job).where(Job.id == job_id).values(dispatched_at=None))

    def delete_job(self, job_id: str, tenant: str) -> Deleted:
        """Delete a finished job of `tenant` with its parts, events and logs (not while it is
        queued or running, nor while a queued or running job needs its results); the jobs
        made from it forget it (`source_job_id`)."""
        with self.session() as s:  # type: ignore[attr-defined]
            job = s.scalar(select(Job).where(Job.id == job_id, Job.tenant == tenant)
                           .with_for_update())
            if job is None:
                return Deleted("missing")
            if job.state in ACTIVE:
                return Deleted("refused", f"job {job_id} is {job.state}; cancel it first")
            needed = self.dependents(s, job_id)
            if needed:
                return Deleted("refused", f"render job {needed[0]} needs the results of job "
                                          f"{job_id}; cancel it or wait for it to end, then "
                                          "delete")
            s.execute(update(Job).where(Job.source_job_id == job_id).values(source_job_id=None))
            parts = delete_parts(s, job_id)
            s.delete(job)
        return Deleted("deleted", ids=[job_id, *parts])

    def job_counts(self, tenant: str) -> dict[str, int]:
        """How many jobs of `tenant` are in each state (parts included); states without one
        are absent."""
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            return {state: int(n) for state, n in s.execute(
                select(Job.state, func.count()).where(Job.tenant == tenant)
                .group_by(Job.state))}

    # -- artifacts (the caller has checked that the job is the tenant's) ----------------------
    def artifact_page(self, job_id: str, *, kind: str | None, frame: str | None,
                      after: str | None, limit: int) -> tuple[list[Artifact], str | None]:
        """The job's artifacts by path after the path `after`, optionally of one kind and one
        frame, and the last path when another page follows (None on the last)."""
        q = select(Artifact).where(Artifact.job_id == job_id)
        if kind is not None:
            q = q.where(Artifact.kind == kind)
        if frame is not None:
            q = q.where(Artifact.frame == frame)
        if after is not None:
            q = q.where(Artifact.path > after)
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            rows = list(s.scalars(q.order_by(Artifact.path).limit(limit + 1)))
        if len(rows) <= limit:
            return rows, None
        return rows[:limit], rows[limit - 1].path

    def artifacts(self, job_id: str) -> list[Artifact]:
        """Every artifact of the job, by path."""
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            return list(s.scalars(select(Artifact).where(Artifact.job_id == job_id)
                                  .order_by(Artifact.path)))

    def artifact(self, job_id: str, path: str) -> Artifact | None:
        """The job's artifact at `path` (None: it has none there)."""
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            return s.scalar(select(Artifact).where(Artifact.job_id == job_id,
                                                   Artifact.path == path))

    # -- captures ---------------------------------------------------------------------------
    def add_capture(self, row: Capture) -> None:
        with self.session() as s:  # type: ignore[attr-defined]
            s.add(row)

    def capture(self, capture_id: str, tenant: str) -> Capture | None:
        """The tenant's capture, its manifest not loaded (None: none of the tenant's)."""
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            return s.scalar(select(Capture).options(defer(Capture.manifest))
                            .where(Capture.id == capture_id, Capture.tenant == tenant))

    def capture_summary(self, capture_id: str) -> dict[str, Any]:
        """The summary its commit gave the capture (empty once it is deleted)."""
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            summary = s.scalar(select(Capture.summary).where(Capture.id == capture_id))
        return summary or {}

    def capture_page(self, tenant: str, state: str | None, after: Key | None,
                     limit: int) -> tuple[list[Capture], Key | None]:
        """The tenant's captures (their manifests not loaded), newest first (`newest_page`)."""
        q = select(Capture).options(defer(Capture.manifest)).where(Capture.tenant == tenant)
        if state is not None:
            q = q.where(Capture.state == state)
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            return newest_page(s, q, Capture.created_at, Capture.id, after, limit)

    def amend_manifest(self, capture_id: str, tenant: str,
                       edit: Callable[[Capture], set[str]]) -> tuple[Capture | None, list[str]]:
        """Run `edit` on the tenant's capture row, locked (it changes the manifest and returns
        the paths whose received copy is stale; what it raises rolls everything back), then
        terminate the uploads of those paths. Returns (the capture, None when there is none;
        the terminated uploads' ids, whose parts the caller deletes)."""
        with self.session() as s:  # type: ignore[attr-defined]
            c = s.scalar(select(Capture).where(Capture.id == capture_id,
                                               Capture.tenant == tenant).with_for_update())
            if c is None:
                return None, []
            changed = edit(c)
            stale = list(s.scalars(select(Upload.id).where(
                Upload.capture_id == capture_id, Upload.path.in_(changed),
                Upload.state.in_(("receiving", "received", "corrupt"))))) if changed else []
            if stale:
                s.execute(update(Upload).where(Upload.id.in_(stale)).values(state="terminated"))
            return c, stale

    def delete_capture(self, capture_id: str, tenant: str) -> Deleted:
        """Delete the tenant's capture row (not while a queued or running job uses it, nor
        while it is being validated); jobs made from it keep their results."""
        with self.session() as s:  # type: ignore[attr-defined]
            c = s.scalar(select(Capture).options(defer(Capture.manifest))
                         .where(Capture.id == capture_id, Capture.tenant == tenant))
            if c is None:
                return Deleted("missing")
            busy = s.scalar(select(Job.id).where(Job.capture_id == capture_id,
                                                 Job.state.in_(ACTIVE)).limit(1))
            if busy is not None:
                return Deleted("refused", f"job {busy} uses capture {capture_id}; cancel it "
                                          "first")
            if c.state == "committing":
                return Deleted("refused", f"capture {capture_id} is being validated; delete "
                                          "it after", retryable=True)
            s.delete(c)
        return Deleted("deleted", ids=[capture_id])

    def remove_capture(self, capture_id: str) -> None:
        """Delete a capture's row whatever its state (an archive upload that failed)."""
        with self.session() as s:  # type: ignore[attr-defined]
            s.execute(delete(Capture).where(Capture.id == capture_id))

    def upload(self, upload_id: str, tenant: str) -> Upload | None:
        """The tenant's upload (None: none of the tenant's)."""
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            return s.scalar(select(Upload).where(Upload.id == upload_id,
                                                 Upload.tenant == tenant))

    # -- assets ------------------------------------------------------------------------------
    @staticmethod
    def asset_users(s: Session, tenant: str, asset_id: str) -> list[str]:
        """Queued or running jobs of `tenant` that use asset `asset_id` (`assets_named`)."""
        rows = s.execute(select(Job.id, Job.params).where(
            Job.tenant == tenant, Job.state.in_(ACTIVE)))
        return [job_id for job_id, params in rows if asset_id in assets_named(params)]

    def asset(self, asset_id: str, tenant: str) -> Asset | None:
        """The tenant's asset (None: none of the tenant's)."""
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            return s.scalar(select(Asset).where(Asset.id == asset_id, Asset.tenant == tenant))

    def add_asset(self, row: Asset) -> None:
        with self.session() as s:  # type: ignore[attr-defined]
            s.add(row)

    def asset_page(self, tenant: str, after: Key | None,
                   limit: int) -> tuple[list[Asset], Key | None]:
        """The tenant's assets, newest first (`newest_page`)."""
        q = select(Asset).where(Asset.tenant == tenant)
        with self.session(write=False) as s:  # type: ignore[attr-defined]
            return newest_page(s, q, Asset.created_at, Asset.id, after, limit)

    def delete_asset(self, asset_id: str, tenant: str) -> Deleted:
        """Delete the tenant's asset row (not while a queued or running job uses it); the
        caller deletes its file."""
        with self.session() as s:  # type: ignore[attr-defined]
            row = s.scalar(select(Asset).where(Asset.id == asset_id, Asset.tenant == tenant)
                           .with_for_update())
            if row is None:
                return Deleted("missing")
            users = self.asset_users(s, tenant, asset_id)
            if users:
                return Deleted("refused", f"job {users[0]} uses asset {asset_id}; cancel it "
                                          "or wait for it to end, then delete")
            s.delete(row)
        return Deleted("deleted", ids=[asset_id])
