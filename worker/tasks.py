"""Thin Celery tasks: they receive a job id and hand it to `worker.runner`, which loads the job
from the store (docs/design.md 2.3); tested with a real worker, not eager mode."""

from __future__ import annotations

import gc
import logging
import time

from celery.signals import worker_process_init

from worker.app import app
from worker.celery_app import TASK_NAME
from worker.faults import hang_if_asked
from worker.gate import nothing_to_run
from worker.pipelines import PIPELINES
from worker.settings import WorkerSettings, get_settings
from worker.store import JobStore

__all__ = ["run_job"]

log = logging.getLogger("dgs.worker")


@worker_process_init.connect
def _load_the_runner(**_) -> None:
    """A pool process loads torch, the runner and every pipeline's job as it starts, while it
    waits for work, so its first job starts as fast as the ones after it (the process is kept
    for many, worker.celery_app): an idle worker's first job waited 1.9 s for these imports.
    What they made lives as long as the process: it is frozen out of the garbage collector,
    whose full pass after each job (`worker.runner`) took 0.19 s of every hand-over to another
    tenant's job walking torch's objects, and now takes microseconds. Only pool processes: the
    Celery parent never loads torch."""
    # lazy: at the pool process's start, never in the Celery parent (it never loads torch)
    import worker.runner  # noqa: F401

    for pipeline in PIPELINES.values():
        pipeline.execution_class()
    gc.collect()
    gc.freeze()


@app.task(name=TASK_NAME, acks_late=True, reject_on_worker_lost=True,
          Request="worker.gate:JobRequest")
def run_job(job_id: str) -> str:
    """Run job `job_id` to its end (idempotent: a message for a job that has ended, was
    deleted or runs on another live worker finds nothing to do, says so in the log and is
    acknowledged; no retry, no traceback). Most such messages never get here: the Celery
    parent drops them (worker.gate)."""
    started = time.monotonic()
    hang_if_asked("start")
    settings = get_settings()
    # Between the parent's look (worker.gate) and here the job may have been cancelled or
    # claimed elsewhere: one read drops such a message before a Runner is made.
    refused = JobStore(settings.database).peek(job_id)
    if refused is not None:
        log.info("job %s: %s (before its run)", job_id, nothing_to_run(refused))
        return refused.status
    # lazy: the Celery parent, which only hands tasks to its pool, never loads torch
    from worker.runner import Runner

    outcome = Runner(settings).run(job_id)
    if outcome.note:
        log.info("job %s: %s", job_id, outcome.note)
    status = outcome.status
    while outcome.gave_way and (handed := _hand_over(settings, job_id, started)) is not None:
        log.info("job %s: handed to this pool process after job %s gave its worker up (no "
                 "process start)", handed, job_id)
        job_id = handed
        outcome = Runner(settings).run(job_id, handed=True)
        if outcome.note:
            log.info("job %s: %s", job_id, outcome.note)
    return status


def _hand_over(settings: WorkerSettings, job_id: str, started: float) -> str | None:
    """The waiting job this pool process runs next, now that its job `job_id` gave its worker
    to another tenant (`worker.fair`): the turn passes at once, without a round trip through
    the broker, and the slot cannot go to another message of the tenant that gave it up. The
    handed job runs under this task's time limit, so only when at least half of its own is
    left (reaching it sends the job back to the queue, `Runner.run`); its own message,
    delivered later, finds it running or ended and is dropped (`worker.gate`)."""
    soft = (run_job.request.timelimit or (None, None))[1]
    left = None if soft is None else soft - (time.monotonic() - started)
    fits = [name for name, p in PIPELINES.items()
            if left is None or left >= p.limits(settings)[0] / 2]
    store = JobStore(settings.database)
    job = store.get(job_id)
    if job is None or not fits:
        return None
    return store.hand_over(job.tenant, settings.stall_seconds, pipelines=fits)
