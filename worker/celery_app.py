"""The Celery application, configured from settings (docs/design.md section 4), and dispatch.

Torch-free: the API builds the same app to send jobs (`dispatch`) without importing the tasks;
`worker.app` is the module `celery -A worker.app worker` loads, with the tasks registered.
"""

from __future__ import annotations

from celery import Celery
from kombu.transport import sqlalchemy as kombu_sqlalchemy

from worker.pipelines import get_pipeline
from worker.settings import WorkerSettings

__all__ = ["TASK_NAME", "dispatch", "make_celery"]

TASK_NAME = "dgs.run_job"


BROKER_POLL_SECONDS = 0.1
"""How often a worker on the SQLite broker looks at an empty queue (Kombu's default, 1 s, was
most of a small job's start: benchmarks/fairness.py measured 0.1-2.3 s). A look is a short
write lock on the broker's file: ten a second a worker."""


class SQLiteTransport(kombu_sqlalchemy.Transport):
    """Kombu's SQLAlchemy transport, looking at an empty queue every `BROKER_POLL_SECONDS`. Its
    `polling_interval` transport option would reach `create_engine` too, which refuses it; a
    class named by Celery's `broker_transport` is the way Kombu leaves."""

    polling_interval = BROKER_POLL_SECONDS


def make_celery(settings: WorkerSettings, *, include: tuple[str, ...] = ()) -> Celery:
    """A Celery app on the settings' broker: acks late, requeue when the worker process is lost
    (the redelivery cap is counted in the job store), one task prefetched, pool processes that
    start as fresh interpreters and run tasks until a count or a memory cap replaces them, no
    result backend (the job store holds every outcome)."""
    broker, transport_class, transport = settings.broker, None, {}
    if broker.startswith(("redis://", "rediss://")):
        transport["visibility_timeout"] = settings.visibility_timeout
        if settings.redis_key_prefix:
            transport["global_keyprefix"] = settings.redis_key_prefix
    elif broker.startswith("sqla+sqlite"):
        broker, transport_class = broker.split("+", 1)[1], f"{__name__}:SQLiteTransport"
        # Kombu hands these to create_engine: wait for the API's writes instead of failing.
        transport["connect_args"] = {"timeout": 30}
    app = Celery("dgs", broker=broker, include=list(include))
    app.conf.update(
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        # A pool process runs up to this many tasks, and none after one that grew it past the
        # memory cap: the next job starts without an interpreter and torch to load.
        worker_max_tasks_per_child=settings.pool_tasks_per_process,
        worker_max_memory_per_child=(None if settings.pool_process_max_mib is None
                                     else settings.pool_process_max_mib * 1024),  # KiB
        # Each pool process starts as a fresh interpreter: a forked one inherited the locks
        # another thread of this process held in SQLite at the fork, and hung in gc (issue 42).
        worker_pool_start_method="spawn",
        # ... which, on a busy machine, takes longer than Celery's 4 s to report for work.
        worker_proc_alive_timeout=120.0,
        # A pool process that ended itself (a cancel's grace ran out) or died has written its
        # outcome to the job store already; Celery need not wait its default 10 s for a result
        # before freeing the slot (the fair pick saw the next tenant wait 10-13 s for it).
        worker_lost_wait=1.0,
        task_default_queue=settings.queue,
        task_ignore_result=True,
        task_serializer="json",
        accept_content=["json"],
        broker_transport=transport_class,
        broker_transport_options=transport,
        broker_connection_retry_on_startup=True,
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
        task_send_sent_event=False,
        enable_utc=True,
    )
    return app


def dispatch(app: Celery, settings: WorkerSettings, job_id: str, pipeline: str) -> None:
    """Send a job to the workers (ids only; the task loads everything from the job store)."""
    soft, hard = get_pipeline(pipeline).limits(settings)
    app.send_task(TASK_NAME, args=[job_id], queue=settings.queue, soft_time_limit=soft,
                  time_limit=hard)
