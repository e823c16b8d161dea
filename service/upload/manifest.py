"""Checks on the paths clients name (manifest entries, tus metadata, archive members) before any
of them touches a file system: relative POSIX paths that cannot leave the capture folder."""

from __future__ import annotations

from collections.abc import Iterable

from core.data.rules import path_problem
from service.errors import ApiError
from service.settings import ServiceSettings

__all__ = ["CANONICAL_DIRS", "check_manifest", "check_path", "path_problem"]

CANONICAL_DIRS = ("images", "masks", "normals")
CANONICAL_FILES = ("capture.json", "points.ply")  # points.ply: optional seed points
# The rule itself is core's (core.data.rules.path_problem): the importers hold the paths their
# metadata names to it too.


def check_path(path: object, where: str, max_bytes: int = 1024) -> str:
    """`path` if it is safe, else ApiError 400 naming it and `where` it came from."""
    problem = path_problem(path, max_bytes)
    if problem is not None:
        raise ApiError(400, f"{where}: path {path!r} {problem}",
                       details=[{"path": where, "message": f"{path!r} {problem}"}])
    assert isinstance(path, str)
    return path


def _canonical_problem(path: str) -> str | None:
    if path in CANONICAL_FILES:
        return None
    top, _, rest = path.partition("/")
    if top in CANONICAL_DIRS and rest:
        return None
    return ("is not part of a canonical capture (capture.json, points.ply, images/, masks/, "
            "normals/); leave it out or use format auto or an importer's format")


def check_manifest(files: Iterable[tuple[str, int]], fmt: str,
                   settings: ServiceSettings) -> int:
    """Check (path, size) pairs against the limits and each other; returns the total size or
    raises ApiError 422 listing up to 100 problems (413 when a limit is exceeded)."""
    problems: list[dict[str, str]] = []
    seen: dict[str, None] = {}  # ordered, so problems come in manifest order
    total = count = 0
    for path, size in files:
        count += 1
        problem = path_problem(path, settings.max_path_bytes)
        if problem is None and fmt == "canonical":
            problem = _canonical_problem(path)
        if problem is None and path in seen:
            problem = "is listed twice"
        if problem is None and size > settings.max_file_bytes:
            problem = f"is {size} bytes; the limit per file is {settings.max_file_bytes}"
        if problem is None and path.endswith(".json") and size > settings.max_json_file_bytes:
            problem = (f"is {size} bytes; a JSON file (parsed whole, in memory) may have "
                       f"{settings.max_json_file_bytes}")
        if problem is not None:
            problems.append({"path": str(path), "message": f"{path!r} {problem}"})
        seen[path] = None
        total += size
    if count > settings.max_capture_files:
        raise ApiError(413, f"manifest lists {count} files; the limit is "
                            f"{settings.max_capture_files}")
    if total > settings.max_capture_bytes:
        raise ApiError(413, f"capture is {total} bytes; the limit is "
                            f"{settings.max_capture_bytes}")
    for path in seen:  # a file cannot also be a folder of another file
        parts = path.split("/")
        for i in range(1, len(parts)):
            parent = "/".join(parts[:i])
            if parent in seen:
                problems.append({"path": path, "message": f"{parent!r} is listed as a file "
                                                          f"and as a folder of {path!r}"})
                break
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise ApiError(422, f"manifest: {problems[0]['message']}{more}", details=problems[:100])
    return total
