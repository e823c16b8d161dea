"""One router per resource (STYLE.md 11)."""

__all__ = ["artifacts", "assets", "captures", "exports", "info", "jobs", "renders",
           "uploads"]
