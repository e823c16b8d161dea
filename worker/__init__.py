"""Celery worker and its thin tasks. Filled in by the service issue."""

__all__: list[str] = []
