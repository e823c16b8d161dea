"""What runs around every request: the strict query-string rule, and the headers a browser may
read across origins. (JSON bodies are limited and parsed by their routes: service.body.)"""

from __future__ import annotations

from fastapi import Request

from service.errors import ApiError

__all__ = ["EXPOSED", "strict_query"]

# Response headers browsers may read on another origin (tus clients need the tus ones).
EXPOSED = ["Location", "Upload-Offset", "Upload-Length", "Upload-Metadata", "Tus-Version",
           "Tus-Resumable", "Tus-Max-Size", "Tus-Extension", "Tus-Checksum-Algorithm", "ETag",
           "Content-Range", "Accept-Ranges", "Content-Disposition", "Idempotent-Replayed",
           "Retry-After"]


_QUERY_NAMES: dict[int, frozenset[str]] = {}


def _query_names(route) -> frozenset[str]:
    """The query parameters of a route and its dependencies (routes live as long as the app)."""
    names = _QUERY_NAMES.get(id(route))
    if names is None:
        found, todo = set(), [route.dependant]
        while todo:
            dependant = todo.pop()
            found |= {q.alias for q in dependant.query_params}
            todo += dependant.dependencies
        names = _QUERY_NAMES[id(route)] = frozenset(found)
    return names


async def strict_query(request: Request) -> None:
    """400 for a query parameter the operation does not take: a typo in a filter
    (`?stat=failed`) must not silently list everything. (async: no I/O, so no worker
    thread.)"""
    route = request.scope.get("route")
    if route is None or not hasattr(route, "dependant"):
        return
    known = _query_names(route)
    unknown = [name for name in request.query_params if name not in known]
    if unknown:
        raise ApiError(400, f"unknown query parameter {unknown[0]!r}; this operation takes "
                            f"{', '.join(sorted(known)) or 'none'}",
                       details=[{"path": f"query.{name}", "message": "unknown parameter"}
                                for name in unknown])
