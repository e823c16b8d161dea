"""The web page at `/` (issue 9): static files from service/web (plain ES modules and CSS, no
build step, no third-party code), served by the API itself so the page works offline.

The page reaches the API only from its own origin, with the key in the Authorization header;
the Content-Security-Policy allows nothing else (no inline script, no other origin), so an
injected string cannot run code or send the key anywhere."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from starlette.staticfiles import StaticFiles
from starlette.types import Message, Receive, Scope, Send

__all__ = ["WEB_DIR", "mount_web"]

WEB_DIR = Path(__file__).resolve().parent / "web"
CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; "
       "media-src 'self' blob:; connect-src 'self'; object-src 'none'; base-uri 'none'; "
       "frame-ancestors 'none'; form-action 'self'")
HEADERS = {"Content-Security-Policy": CSP, "X-Content-Type-Options": "nosniff",
           "Referrer-Policy": "no-referrer", "Cache-Control": "no-cache"}


class _Headers:
    """Adds the page's security headers to every answer of the wrapped app."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        async def send_with(message: Message) -> None:
            if message["type"] == "http.response.start":
                names = {k.lower() for k, _ in message.get("headers", [])}
                extra = [(k.lower().encode(), v.encode()) for k, v in HEADERS.items()
                         if k.lower().encode() not in names]
                message = {**message, "headers": [*message.get("headers", []), *extra]}
            await send(message)

        await self.app(scope, receive, send_with)


def mount_web(app: FastAPI) -> None:
    """`GET /` answers the page; `/web/...` its scripts, styles and icon."""

    @app.get("/", include_in_schema=False)
    def web_page() -> FileResponse:
        return FileResponse(WEB_DIR / "index.html", media_type="text/html", headers=HEADERS)

    app.mount("/web", _Headers(StaticFiles(directory=WEB_DIR)), name="web")
