"""The API side of jobs run as parts (docs/design.md 4.4): whether a posted reconstruction is
split (the groups of its resolved run), a parent's parts and overall progress as the API shows
them."""

from __future__ import annotations

from core.config import ResolvedRun, independent_groups
from service.deps import Services
from service.schemas import PartOut
from worker.models import Job
from worker.parts import overall_progress, part_out
from worker.store import progress_of

__all__ = ["job_parts", "split_job"]


def split_job(resolved: ResolvedRun) -> list[list[str]] | None:
    """The frames of each part of a reconstruct job (one per group of pictures of its run,
    `core.config.independent_groups`), or None when it runs as one (a single group, or groups
    that depend on each other)."""
    groups = independent_groups(resolved.frames, resolved.config)
    return [list(g.frames) for g in groups] if groups is not None and len(groups) > 1 else None


def job_parts(services: Services, job: Job) -> tuple[list[PartOut] | None, dict]:
    """The parts of `job` as the API shows them (None for a job that runs as one) and its
    progress (over its parts while they run)."""
    progress = progress_of(job)
    if not job.parts:
        return None, progress
    parts = services.store.parts(job.id)
    progress.update(overall_progress(job, parts))
    return [PartOut(**part_out(p)) for p in parts], progress
