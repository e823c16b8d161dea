"""Thin Celery tasks: they receive a job id and hand it to `worker.runner` (STYLE.md 10)."""

from __future__ import annotations

from worker.app import app
from worker.celery_app import TASK_NAME
from worker.settings import get_settings

__all__ = ["run_job"]


@app.task(name=TASK_NAME, bind=True, acks_late=True, reject_on_worker_lost=True)
def run_job(self, job_id: str) -> str:
    """Run job `job_id` to its end (idempotent: a job finished, cancelled or run by another
    worker is left alone). A job leased by a live worker is tried again when the lease ends."""
    from worker.runner import Runner

    outcome = Runner(get_settings()).run(job_id)
    if outcome.retry_in is not None:
        raise self.retry(countdown=outcome.retry_in, max_retries=None)
    return outcome.status
