"""Celery workers and the job contract the API shares with them (job store, artifact store,
pipelines, settings). Importing this package, or any module the API uses, never imports torch;
only `worker.runner` reaches core's training code, inside the worker process."""

__all__ = [
    "artifacts",
    "blobs",
    "celery_app",
    "db",
    "models",
    "pipelines",
    "settings",
    "store",
]
