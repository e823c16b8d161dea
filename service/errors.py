"""Every error the API answers is `{"error": {"code", "message", "retryable", "details"}}` with a
real HTTP status (docs/design.md 3.5): raised as `ApiError` by the routers, and converted here from
FastAPI's validation errors, Starlette's 404/405 and any unhandled exception (500)."""

from __future__ import annotations

import logging
import sys
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from sqlalchemy.exc import InterfaceError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

__all__ = [
    "COMMON",
    "ApiError",
    "ErrorDetail",
    "ErrorInfo",
    "ErrorOut",
    "body_problem",
    "error_responses",
    "install_error_handlers",
]

log = logging.getLogger("dgs.service")

# The code of errors raised without one, by status.
CODES = {400: "invalid_request", 401: "unauthorized", 403: "forbidden", 404: "not_found",
         405: "method_not_allowed", 409: "conflict", 411: "length_required",
         412: "precondition_failed", 413: "payload_too_large", 415: "unsupported_media_type",
         416: "range_not_satisfiable", 422: "invalid_request", 429: "too_many_requests",
         460: "checksum_mismatch",
         500: "internal", 501: "not_implemented", 503: "unavailable",
         507: "insufficient_storage"}
TUS_PREFIX = "/v1/uploads"
RETRY_AFTER_SECONDS = 5
"""Retry-After of a 503 while the job store is unreachable."""
COMMON = (400, 401, 404, 422, 500)
"""Errors any /v1 operation may answer (malformed input, no key, not found, invalid, bug)."""


class ErrorDetail(BaseModel):
    """One problem of several: the file, field or path it concerns and what is wrong."""

    path: str | None = Field(None, description="File, field or header the problem concerns.")
    message: str


class ErrorInfo(BaseModel):
    code: str = Field(description="Stable machine-readable code, e.g. not_found, conflict, "
                                  "invalid_capture, checksum_mismatch.")
    message: str = Field(description="What went wrong and what to do about it.")
    retryable: bool = Field(description="True when the same request may succeed later.")
    details: list[ErrorDetail] = Field(default_factory=list)


class ErrorOut(BaseModel):
    error: ErrorInfo


class ApiError(Exception):
    """An error answer: status, code, message, retryable, optional details and headers."""

    def __init__(self, status: int, message: str, *, code: str | None = None,
                 retryable: bool = False, details: list[dict[str, Any]] | None = None,
                 headers: dict[str, str] | None = None):
        super().__init__(message)
        self.status, self.message = status, message
        self.code = code or CODES.get(status, "error")
        self.retryable, self.details, self.headers = retryable, details or [], headers or {}

    def body(self) -> dict[str, Any]:
        return {"error": {"code": self.code, "message": self.message,
                          "retryable": self.retryable, "details": self.details}}


RETRY_AFTER = {"Retry-After": {"description": "Seconds to wait before sending it again.",
                               "schema": {"type": "integer", "minimum": 1}}}


def error_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries for these error statuses (all share ErrorOut; a 429 says
    that it comes with Retry-After)."""
    return {status: {"model": ErrorOut, "description": CODES.get(status, "error"),
                     **({"headers": RETRY_AFTER} if status == 429 else {})}
            for status in statuses}


def _respond(request: Request, error: ApiError) -> JSONResponse:
    headers = dict(error.headers)
    if request.url.path.startswith(TUS_PREFIX):
        headers.setdefault("Tus-Resumable", "1.0.0")
    if error.status == 401:
        headers.setdefault("WWW-Authenticate", 'Bearer realm="dgs"')
    return JSONResponse(error.body(), status_code=error.status, headers=headers)


async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
    return _respond(request, exc)


def body_problem(cause: BaseException) -> str:
    """Why a JSON body could not be parsed (FastAPI answers only "There was an error parsing
    the body" and keeps the reason as the exception's cause; service.body asks directly)."""
    if isinstance(cause, UnicodeDecodeError):
        return (f"body: not UTF-8 text (byte {cause.start} is {cause.object[cause.start]:#04x});"
                " send JSON encoded as UTF-8")
    if isinstance(cause, RecursionError):
        return "body: the JSON is nested too deeply to parse"
    if isinstance(cause, ValueError) and "integer string conversion" in str(cause):
        return f"body: a JSON number has more than {sys.get_int_max_str_digits()} digits"
    return f"body: not valid JSON ({cause})"


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    message = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
    if exc.status_code == 400 and exc.__cause__ is not None and \
            message == "There was an error parsing the body":
        problem = body_problem(exc.__cause__)
        return _respond(request, ApiError(422, problem, details=[
            {"path": "body", "message": problem.removeprefix("body: ")}]))
    if exc.status_code == 404 and message == "Not Found":
        message = f"no such endpoint: {request.method} {request.url.path}"
    headers = dict(exc.headers or {})
    if exc.status_code == 405:
        allowed = _allowed(request)
        headers["Allow"] = ", ".join(allowed)
        message = f"{request.method} is not allowed on {request.url.path}; use {headers['Allow']}"
    return _respond(request, ApiError(exc.status_code, message, headers=headers,
                                      retryable=exc.status_code >= 500))


def _allowed(request: Request) -> list[str]:
    """Every method some route serves at this path (Starlette names only the first route's)."""
    scope = {"type": "http", "path": request.url.path, "root_path": ""}
    return [m for m in ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")
            if any(r.matches({**scope, "method": m})[0] == Match.FULL
                   for r in request.app.routes)]


def _where(loc: tuple[Any, ...] | list[Any]) -> str:
    return ".".join(str(part) for part in loc)


def _detail(error: dict[str, Any]) -> dict[str, str]:
    if error.get("type") == "json_invalid":  # loc is ("body", character offset)
        where = error.get("loc", ("body", "?"))[-1]
        reason = (error.get("ctx") or {}).get("error", "JSON decode error")
        return {"path": "body", "message": f"not valid JSON at character {where}: {reason}"}
    return {"path": _where(error.get("loc", ())), "message": error.get("msg", "invalid")}


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    details = [_detail(e) for e in exc.errors()]
    first = details[0] if details else {"path": "", "message": "invalid request"}
    more = f" (and {len(details) - 1} more)" if len(details) > 1 else ""
    return _respond(request, ApiError(422, f"{first['path']}: {first['message']}{more}",
                                      details=details))


STORE_DOWN = (OperationalError, InterfaceError, PoolTimeout)
"""What SQLAlchemy raises when the job store cannot be reached or has no connection to spare:
the service is unavailable for a moment, nothing is wrong with the request."""


async def _store_down(request: Request, exc: Exception) -> JSONResponse:
    log.warning("%s %s: the job store is unreachable (%s)", request.method, request.url.path,
                str(exc).splitlines()[0][:300])
    return _respond(request, ApiError(
        503, "the job store is unreachable; try again in a moment", retryable=True,
        headers={"Retry-After": str(RETRY_AFTER_SECONDS)}))


async def _unhandled(request: Request, exc: Exception) -> JSONResponse:
    if isinstance(exc, STORE_DOWN):  # raised outside a route (a middleware): the same answer
        return await _store_down(request, exc)
    log.exception("unhandled error in %s %s", request.method, request.url.path)
    return _respond(request, ApiError(500, "internal error; it is logged on the server",
                                      retryable=True))


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    for kind in STORE_DOWN:
        app.add_exception_handler(kind, _store_down)
    app.add_exception_handler(Exception, _unhandled)
