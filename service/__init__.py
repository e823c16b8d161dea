"""HTTP service (FastAPI). Filled in by the service issue; it never imports torch."""

__all__: list[str] = []
