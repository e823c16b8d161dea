"""The API side of jobs run as parts (docs/design.md 4.4): whether a posted reconstruction is
split (its frames read from the frozen capture.json), a parent's parts and overall progress as
the API shows them."""

from __future__ import annotations

import json

from core.config import parse_frames
from service.deps import Services
from service.schemas import PartOut
from worker.models import Capture, Job
from worker.parts import overall_progress, part_out, split_frames
from worker.pipelines import ReconstructParams
from worker.store import progress_of

__all__ = ["job_parts", "split_job"]


def split_job(services: Services, capture: Capture,
              params: ReconstructParams) -> list[list[str]] | None:
    """The frames of each part of a reconstruct job (one per group of pictures), or None when
    it runs as one (a single group, or groups that depend on each other)."""
    key = f"captures/{capture.id}/capture.json"
    size = services.blobs.size(key)
    if size is None:
        return None
    frames = json.loads(b"".join(services.blobs.read_range(key, 0, size))).get("frames") or []
    chosen = parse_frames(params.frames, [str(f) for f in frames])
    return split_frames(chosen, params.run_config())


def job_parts(services: Services, job: Job) -> tuple[list[PartOut] | None, dict]:
    """The parts of `job` as the API shows them (None for a job that runs as one) and its
    progress (over its parts while they run)."""
    progress = progress_of(job)
    if not job.parts:
        return None, progress
    parts = services.store.parts(job.id)
    progress.update(overall_progress(job, parts))
    return [PartOut(**part_out(p)) for p in parts], progress
