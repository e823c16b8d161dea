"""Celery workers and the job contract the API shares with them (job store, artifact store,
pipelines, settings). Importing this package, or any module the API uses, never imports torch;
only `worker.runner` and the job executions it runs (`*_job.py`) reach core's training code,
inside the worker process."""

__all__ = [
    "blobs",
    "celery_app",
    "db",
    "models",
    "parts",
    "pipelines",
    "settings",
    "store",
]
