"""What runs around every request: the body limit of buffered (JSON) requests, the strict
query-string rule, and the headers a browser may read across origins."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import ApiError

__all__ = ["EXPOSED", "STREAMED", "BodyLimit", "strict_query"]

# Response headers browsers may read on another origin (tus clients need the tus ones).
EXPOSED = ["Location", "Upload-Offset", "Upload-Length", "Upload-Metadata", "Tus-Version",
           "Tus-Resumable", "Tus-Max-Size", "Tus-Extension", "Tus-Checksum-Algorithm", "ETag",
           "Content-Range", "Accept-Ranges", "Content-Disposition"]
# Requests whose body the route streams itself, under its own limit.
STREAMED = (("PATCH", "/v1/uploads/"), ("POST", "/v1/captures/archive"),
            ("POST", "/v1/assets"))


class BodyLimit:
    """Refuses (413) a buffered request body over `limit` bytes before FastAPI reads it (a
    manifest is JSON; without a bound one request could take the memory of the process)."""

    def __init__(self, app: ASGIApp, limit: int):
        self.app, self.limit = app, limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS") or any(
                scope["method"] == m and scope["path"].startswith(p) for m, p in STREAMED):
            return await self.app(scope, receive, send)
        body, more = [], True
        size = 0
        while more:
            message = await receive()
            if message["type"] != "http.request":
                return  # the client left
            body.append(message.get("body", b""))
            size += len(body[-1])
            more = message.get("more_body", False)
            if size > self.limit:
                error = ApiError(413, f"request body passes the limit of {self.limit} bytes")
                return await _send_error(error, scope, send)
        replay: list[Message] = [{"type": "http.request", "body": b"".join(body),
                                  "more_body": False}]

        async def replayed() -> Message:
            return replay.pop() if replay else await receive()

        await self.app(scope, replayed, send)


async def _send_error(error: ApiError, scope: Scope, send: Send) -> None:
    response = JSONResponse(error.body(), status_code=error.status)
    await response(scope, _no_body, send)


async def _no_body() -> Message:
    return {"type": "http.disconnect"}


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
