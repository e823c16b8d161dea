"""One router per resource (docs/design.md 2.1)."""

__all__ = ["artifacts", "assets", "captures", "exports", "info", "jobs", "renders",
           "uploads"]
