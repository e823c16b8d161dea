"""JSON request bodies, read and parsed at the door (docs/design.md 3.5): every route that takes
one (`JsonRoute`, the route class of every router) reads it under its own byte limit, refusing
with 413 by Content-Length before reading a byte when it can, and parses and validates it in a
worker thread, so a large or hostile body never holds the event loop (and /healthz) while it is
decoded. Bodies the routes stream themselves (tus PATCH, a zip archive, an asset) have no body
field and keep their own limits.

The limit is a ServiceSettings field: `max_json_bytes` unless the endpoint is marked with
`body_limit("max_manifest_bytes")` (a manifest of a million files is about 150 MiB).
Validation goes straight from the JSON text (`validate_json`), so the models' strictness
(`core.config.base.StrictModel`) applies to JSON's own types."""

from __future__ import annotations

import email.message
import json
import re
from collections.abc import Callable
from typing import Any, TypeVar

from fastapi import Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute
from pydantic import TypeAdapter, ValidationError
from starlette.concurrency import run_in_threadpool

from service.errors import ApiError, body_problem

__all__ = ["MAX_ERRORS", "JsonRoute", "body_limit", "content_length", "parse_json_body",
           "read_body"]

F = TypeVar("F", bound=Callable[..., Any])
MAX_ERRORS = 50
"""Most validation problems an answer lists (a body of a million bad items has as many)."""
_LIMIT = "__dgs_body_limit__"
_SPACE = re.compile(rb"[ \t\r\n]*")


def body_limit(setting: str, values: Callable[[Any], int] | None = None) -> Callable[[F], F]:
    """Mark an endpoint whose JSON body is limited by the ServiceSettings field `setting`
    instead of `max_json_bytes`, and (`values(settings)`) to fewer JSON values than that (a
    body this large is counted, at memchr speed, before it is parsed)."""

    def mark(endpoint: F) -> F:
        setattr(endpoint, _LIMIT, (setting, values))
        return endpoint

    return mark


def _is_json(request: Request) -> bool:
    """Whether FastAPI would read the body as JSON (no Content-Type, or application/*json)."""
    value = request.headers.get("content-type")
    if not value:
        return True
    message = email.message.Message()
    message["content-type"] = value
    subtype = message.get_content_subtype()
    return message.get_content_maintype() == "application" and (
        subtype == "json" or subtype.endswith("+json"))


def _too_large(limit: int) -> ApiError:
    return ApiError(413, f"request body passes the limit of {limit} bytes for this operation "
                         "(captures' files go up with tus uploads or a zip archive)")


def content_length(request: Request) -> int | None:
    """The declared Content-Length (None when absent or not a number), bounded before it is
    converted: one of more than 18 digits reads as 10**18, past any limit."""
    declared = request.headers.get("content-length", "")
    if not (declared.isascii() and declared.isdigit()):
        return None
    declared = declared.lstrip("0") or "0"
    return 10 ** 18 if len(declared) > 18 else int(declared)


async def read_body(request: Request, limit: int) -> bytes:
    """The whole body, at most `limit` bytes (413 otherwise: at once when Content-Length says
    so, else as soon as the bytes received pass it)."""
    declared = content_length(request)
    if declared is not None and declared > limit:
        raise _too_large(limit)
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise _too_large(limit)
        chunks.append(chunk)
    return b"".join(chunks)


def _syntax_error(body: bytes, fallback: str) -> Exception:
    """The error for a body that is not JSON, as FastAPI words it (its syntax error's position,
    or why it could not be read); `fallback`: the JSON parser's own reason, for what Python's
    parser takes and pydantic's does not (nesting past 200, a lone surrogate)."""
    try:
        json.loads(body.decode("utf-8"))
    except json.JSONDecodeError as exc:
        return RequestValidationError([{
            "type": "json_invalid", "loc": ("body", exc.pos), "msg": "JSON decode error",
            "input": {}, "ctx": {"error": exc.msg}}])
    except (UnicodeDecodeError, RecursionError, ValueError) as exc:
        problem = body_problem(exc)
    else:
        problem = f"body: not valid JSON ({fallback.removeprefix('Invalid JSON: ')})"
    return ApiError(422, problem, details=[{"path": "body",
                                            "message": problem.removeprefix("body: ")}])


def _shape_error(body: bytes, max_values: int | None) -> Exception | None:
    """What is wrong with the body before it is parsed, found at memchr speed: not an object
    (every request body is one), or more values than the operation can need."""
    first = body[_SPACE.match(body).end():][:1]
    if first != b"{":
        if first and first in b'["-0123456789tfn':
            return ApiError(422, "body: expected a JSON object ({...})", details=[
                {"path": "body", "message": "expected a JSON object ({...})"}])
        return _syntax_error(body, "expected value")
    if max_values is not None and body.count(b",") >= max_values:
        return ApiError(413, f"body: more than {max_values} JSON values; this operation takes "
                             "fewer (see limits in GET /v1/info)")
    return None


def parse_json_body(adapter: TypeAdapter, body: bytes, max_values: int | None = None) -> Any:
    """The validated body (run in a worker thread): its shape checked first (`_shape_error`),
    then parsed and strictly validated in one pass from the JSON text, at most MAX_ERRORS
    problems listed, each under `body`."""
    problem = _shape_error(body, max_values)
    if problem is not None:
        raise problem
    try:
        return adapter.validate_json(body)
    except ValidationError as exc:
        found = exc.errors(include_url=False)[:MAX_ERRORS]
        if any(e["type"] == "json_invalid" for e in found):
            raise _syntax_error(body, found[0]["msg"]) from None
        errors = [{**e, "loc": ("body", *e["loc"])} for e in found]
        if exc.error_count() > MAX_ERRORS:
            errors.append({"type": "too_many_errors", "loc": ("body",), "msg": (
                f"{exc.error_count() - MAX_ERRORS} more problems not listed")})
        raise RequestValidationError(errors) from None


class JsonRoute(APIRoute):
    """An APIRoute whose JSON body is read under its limit and parsed off the event loop (see
    the module's docstring); routes without a body field are left as FastAPI makes them."""

    def get_route_handler(self) -> Callable[[Request], Any]:
        handler = super().get_route_handler()
        if self.body_field is None:
            return handler
        adapter = TypeAdapter(self.body_field.field_info.annotation)
        setting, values = getattr(self.endpoint, _LIMIT, ("max_json_bytes", None))

        async def route(request: Request) -> Response:
            settings = request.app.state.services.settings
            body = await read_body(request, getattr(settings, setting))
            request._body = body  # what FastAPI's handler reads
            if body and _is_json(request):
                request._json = await run_in_threadpool(
                    parse_json_body, adapter, body, values and values(settings))
            return await handler(request)

        return route
