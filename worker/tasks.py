"""Thin Celery tasks: they receive a job id and hand it to `worker.runner`, which loads the job
from the store (docs/design.md 2.3); tested with a real worker, not eager mode."""

from __future__ import annotations

import logging

from worker.app import app
from worker.celery_app import TASK_NAME
from worker.faults import hang_if_asked
from worker.gate import nothing_to_run
from worker.settings import get_settings
from worker.store import JobStore

__all__ = ["run_job"]

log = logging.getLogger("dgs.worker")


@app.task(name=TASK_NAME, acks_late=True, reject_on_worker_lost=True,
          Request="worker.gate:JobRequest")
def run_job(job_id: str) -> str:
    """Run job `job_id` to its end (idempotent: a message for a job that has ended, was
    deleted or runs on another live worker finds nothing to do, says so in the log and is
    acknowledged; no retry, no traceback). Most such messages never get here: the Celery
    parent drops them (worker.gate)."""
    hang_if_asked("start")
    settings = get_settings()
    # Between the parent's look (worker.gate) and here, the seconds a fresh interpreter takes,
    # the job may have been cancelled or claimed elsewhere: one read, before torch is
    # imported (seconds more), drops such a message at the cost of the process alone.
    refused = JobStore(settings.database).peek(job_id)
    if refused is not None:
        log.info("job %s: %s (before loading torch)", job_id, nothing_to_run(refused))
        return refused.status
    # lazy: the Celery parent, which only hands tasks to its pool, never loads torch
    from worker.runner import Runner

    outcome = Runner(settings).run(job_id)
    if outcome.note:
        log.info("job %s: %s", job_id, outcome.note)
    return outcome.status
