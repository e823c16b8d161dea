"""The API never shows a client the server's folders (GUIDE: "never a server path in a
message"). `LeakScan` sees every response the service tests receive, through httpx (TestClient,
the live servers, service.client) and requests (tuspy), and records each error body (status >=
400) and each error or message inside a JSON body (a failed job's error, its log lines) that
names a path under the session's temporary folder, where every test's data and scratch folders
live. A path the request itself sent (echoed back) is the client's, not a leak."""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import httpx
import pytest

SCANNED_KEYS = ("error", "message", "lines")


@dataclass
class Leak:
    method: str
    url: str
    status: int
    text: str


@dataclass
class LeakScan:
    folder: str
    """The session's temporary folder: every data dir and scratch dir is under it."""
    leaks: list[Leak] = field(default_factory=list)
    errors_seen: int = 0
    """Error bodies (status >= 400) scanned, so a test can tell the scan is wired."""

    def texts(self, status: int, body: str) -> list[str]:
        """What of a response body a client reads as an error or a message."""
        if status >= 400:
            self.errors_seen += 1
            return [body]
        try:
            doc = json.loads(body)
        except ValueError:
            return []
        return [json.dumps(v) for v in _values(doc, SCANNED_KEYS)]

    def check(self, method: str, url: str, status: int, body: str, sent: str) -> None:
        if self.folder not in body:
            self.texts(status, body)  # counts error bodies
            return
        for text in self.texts(status, body):
            if self.folder in text and not _echoed(text, self.folder, sent):
                self.leaks.append(Leak(method, url, status, text[:2000]))

    @contextmanager
    def installed(self) -> Iterator[LeakScan]:
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(httpx.Client, "send", _sync_send(self, httpx.Client.send))
            mp.setattr(httpx.AsyncClient, "send", _async_send(self, httpx.AsyncClient.send))
            try:
                import requests
            except ImportError:
                pass
            else:
                mp.setattr(requests.Session, "send", _requests_send(self, requests.Session.send))
            yield self


def _values(doc: Any, keys: tuple[str, ...]) -> Iterator[Any]:
    if isinstance(doc, dict):
        for key, value in doc.items():
            if key in keys and value:
                yield value
            else:
                yield from _values(value, keys)
    elif isinstance(doc, list):
        for item in doc:
            yield from _values(item, keys)


def _echoed(text: str, folder: str, sent: str) -> bool:
    """Every path under `folder` in `text` also appears in what the client sent."""
    at = 0
    while (at := text.find(folder, at)) >= 0:
        end = at
        while end < len(text) and text[end] not in " '\"\n,;)]}":
            end += 1
        if text[at:end] not in sent:
            return False
        at = end
    return True


def _sent(request: httpx.Request) -> str:
    try:
        body = request.content.decode(errors="replace")
    except httpx.RequestNotRead:
        body = ""
    return f"{request.url} {dict(request.headers)} {body}"


def _body(response: httpx.Response) -> str | None:
    if not response.is_stream_consumed and response.status_code < 400:
        return None  # a 2xx stream (events, downloads) the caller reads itself
    try:
        return response.text
    except httpx.ResponseNotRead:
        return None


def _sync_send(scan: LeakScan, send):
    def wrapped(self, request, **kwargs):
        response = send(self, request, **kwargs)
        if kwargs.get("stream") and response.status_code >= 400:
            response.read()  # kept: the caller's reads see the same bytes
        body = _body(response)
        if body is not None:
            scan.check(request.method, str(request.url), response.status_code, body,
                       _sent(request))
        return response

    return wrapped


def _async_send(scan: LeakScan, send):
    async def wrapped(self, request, **kwargs):
        response = await send(self, request, **kwargs)
        if kwargs.get("stream") and response.status_code >= 400:
            await response.aread()
        body = _body(response)
        if body is not None:
            scan.check(request.method, str(request.url), response.status_code, body,
                       _sent(request))
        return response

    return wrapped


def _requests_send(scan: LeakScan, send):
    def wrapped(self, request, **kwargs):
        response = send(self, request, **kwargs)
        if not kwargs.get("stream"):
            body = request.body if isinstance(request.body, str) else (
                request.body.decode(errors="replace") if isinstance(request.body, bytes)
                else "")
            scan.check(request.method, request.url, response.status_code, response.text,
                       f"{request.url} {dict(request.headers)} {body}")
        return response

    return wrapped
