"""The HTTP plumbing of the client: the connection, errors as `ApiError`, JSON calls and cursor
pages."""

from __future__ import annotations

import json
import os
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import httpx

__all__ = ["ApiError", "Event", "Http", "RETRIED", "TERMINAL", "retry_after"]

TERMINAL = ("succeeded", "failed", "cancelled")
RETRIED = (429, 500, 502, 503, 504)
"""Statuses a submit is sent again after (with its Idempotency-Key, that is safe)."""


class ApiError(RuntimeError):
    """An error answer of the API: status, code, message, retryable, details, and the
    seconds its Retry-After asked to wait (None without one)."""

    def __init__(self, status: int, code: str, message: str, retryable: bool = False,
                 details: list[dict] | None = None, retry_after: float | None = None):
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message = status, code, message
        self.retryable, self.details, self.retry_after = retryable, details or [], retry_after


def retry_after(r: httpx.Response) -> float | None:
    """The answer's Retry-After in seconds (the delay form; None when absent or a date)."""
    value = r.headers.get("retry-after", "").strip()
    return float(value) if value.isascii() and value.isdigit() and len(value) <= 9 else None


@dataclass(frozen=True)
class Event:
    """One server-sent event of a job: its id, kind (state, progress, artifact) and data."""

    id: int
    kind: str
    data: dict[str, Any]


class Http:
    """The API at `base_url`, with a bearer key (None when the server has no keys).

    `url_store`: a JSON file where the URLs of begun uploads are kept, so that another
    process (after a crash, a closed laptop) resumes them instead of starting over.
    `chunk_checksum`: None (default) streams each file in one PATCH; a dropped connection
    loses nothing (the server keeps what arrived, HEAD says where to go on) and the server
    checks the whole file against the manifest's SHA-256. "sha1" (or sha256, md5) sends
    CHUNK-byte PATCHes with a tus Upload-Checksum each, so a chunk damaged on the way is
    refused alone and sent again; it costs a hash on both sides and a request per chunk
    (benchmarks/service.py measures both).
    `submit_attempts`: how many times a submit (a job, render or export) is sent when the
    connection fails, times out or the server answers 429 or 5xx, `retry_delay` seconds apart
    (doubling); every submit carries an Idempotency-Key, so the server makes one job however
    many times it arrives. After a 429 (a limit of the server, which then did nothing) the
    wait is the answer's Retry-After, at most `max_wait` seconds, and every JSON request is
    sent again so, as many times; `sleep` is how the client waits (tests pass their own)."""

    def __init__(self, base_url: str, api_key: str | None = None, *, timeout: float = 60.0,
                 transport: httpx.BaseTransport | None = None,
                 url_store: str | os.PathLike[str] | None = None,
                 chunk_checksum: Literal["sha1", "sha256", "md5"] | None = None,
                 submit_attempts: int = 5, retry_delay: float = 0.5, max_wait: float = 60.0,
                 sleep: Callable[[float], None] = time.sleep):
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.http = httpx.Client(base_url=base_url.rstrip("/"), headers=headers,
                                 timeout=timeout, transport=transport)
        self.url_store = Path(url_store) if url_store is not None else None
        self.chunk_checksum = chunk_checksum
        self.submit_attempts, self.retry_delay = max(1, submit_attempts), retry_delay
        self.max_wait, self.sleep = max_wait, sleep
        self._uploads: dict[str, str] = (
            json.loads(self.url_store.read_text()) if self.url_store is not None
            and self.url_store.is_file() else {})
        """Upload URLs by "capture/path": resumed instead of started over."""

    def close(self) -> None:
        self.http.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- plumbing -----------------------------------------------------------------------------
    @staticmethod
    def _check(r: httpx.Response) -> httpx.Response:
        if r.status_code < 400:
            return r
        try:
            err = r.json()["error"]
        except (ValueError, KeyError, TypeError):
            err = {"code": "http_error", "message": r.text[:500]}
        raise ApiError(r.status_code, err.get("code", "?"), err.get("message", ""),
                       bool(err.get("retryable")), err.get("details"), retry_after(r))

    def _wait(self, attempt: int, r: httpx.Response | None = None) -> float:
        """How long to wait before attempt `attempt + 1`: a 429's Retry-After (at most
        `max_wait`), else `retry_delay` doubling."""
        after = retry_after(r) if r is not None and r.status_code == 429 else None
        return min(after, self.max_wait) if after is not None else \
            self.retry_delay * 2 ** attempt

    def _json(self, method: str, url: str, **kw) -> Any:
        """A JSON request, sent again after a 429 (`_wait`), `submit_attempts` times at most."""
        for attempt in range(self.submit_attempts):
            r = self.http.request(method, url, **kw)
            if r.status_code != 429 or attempt + 1 == self.submit_attempts:
                break
            self.sleep(self._wait(attempt, r))
        r = self._check(r)
        return r.json() if r.content else None

    def _submit(self, url: str, body: dict, key: str | None = None) -> dict:
        """POST a submit with an Idempotency-Key (`key`, else a new UUID), sent again with the
        same key after a lost connection, a timeout, 429 (once its Retry-After has passed) or
        a 5xx (see the class docstring)."""
        headers = {"Idempotency-Key": key or str(uuid.uuid4())}
        for attempt in range(self.submit_attempts):
            last, r = attempt + 1 == self.submit_attempts, None
            try:
                r = self.http.post(url, json=body, headers=headers)
            except httpx.TransportError:
                if last:
                    raise
            else:
                if last or r.status_code not in RETRIED:
                    return self._check(r).json()
            self.sleep(self._wait(attempt, r))
        raise AssertionError("unreachable")  # the last attempt returns or raises

    def _pages(self, url: str, params: dict) -> Iterator[dict]:
        cursor = None
        while True:
            page = self._json("GET", url, params={**params, **({"cursor": cursor}
                                                               if cursor else {})})
            yield from page["items"]
            cursor = page.get("next_cursor")
            if not cursor:
                return

    def info(self) -> dict:
        return self._json("GET", "/v1/info")

