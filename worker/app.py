"""The worker's Celery app: `celery -A worker.app worker` (what `dgs worker` runs)."""

from __future__ import annotations

from worker.celery_app import make_celery
from worker.settings import get_settings

__all__ = ["app"]

app = make_celery(get_settings(), include=("worker.tasks",))
