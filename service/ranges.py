"""Downloads of stored blobs with HTTP Range (RFC 9110): one range `bytes=a-b`, `a-` or `-n`
gets 206 with Content-Range; an unsatisfiable one 416 with `Content-Range: bytes */size`;
several ranges, or a syntax this does not understand, the whole body (200), as the RFC allows.
The ETag is the blob's SHA-256: If-None-Match answers 304, If-Range keeps a resumed download
from mixing two versions of a file."""

from __future__ import annotations

import re
from urllib.parse import quote

from fastapi import Request, Response
from fastapi.responses import StreamingResponse

from service.errors import ApiError
from worker.blobs import BlobStore

__all__ = ["blob_response", "parse_range"]

_RANGE = re.compile(r"^\s*bytes\s*=\s*([0-9]*)\s*-\s*([0-9]*)\s*$", re.IGNORECASE)
# A byte position of more digits than this is past any blob (2**63 has 19): it is read as
# BEYOND instead of converted (int() of a 4,300-digit string raises).
MAX_DIGITS = 18
BEYOND = 10 ** MAX_DIGITS


def _position(digits: str) -> int:
    """A byte position of the header, bounded before it is converted: leading zeros dropped,
    anything longer than MAX_DIGITS digits is BEYOND every blob."""
    digits = digits.lstrip("0") or "0"
    return BEYOND if len(digits) > MAX_DIGITS else int(digits)


def parse_range(header: str | None, size: int) -> tuple[int, int] | None | str:
    """(start, end exclusive) of a single satisfiable range; None to send everything;
    "unsatisfiable" for a range outside the blob."""
    if not header or "," in header:
        return None
    m = _RANGE.match(header)
    if m is None or (not m.group(1) and not m.group(2)):
        return None
    first, last = m.group(1), m.group(2)
    if not first:  # the last n bytes
        n = _position(last)
        if n == 0 or size == 0:
            return "unsatisfiable"
        return max(0, size - n), size
    start = _position(first)
    end = _position(last) if last else None
    if end is not None and end < start:
        return None  # invalid: ignored, as RFC 9110 says
    if start >= size:
        return "unsatisfiable"
    return start, min(end + 1, size) if end is not None else size


def _etag_matches(header: str, etag: str) -> bool:
    tags = [t.strip().removeprefix("W/") for t in header.split(",")]
    return "*" in tags or etag in tags


def blob_response(request: Request, blobs: BlobStore, key: str, *, size: int, sha256: str,
                  content_type: str, filename: str) -> Response:
    etag = f'"{sha256}"'
    headers = {"ETag": etag, "Accept-Ranges": "bytes", "Cache-Control": "private, no-cache",
               "Content-Disposition": f"attachment; filename*=UTF-8''{quote(filename)}"}
    inm = request.headers.get("if-none-match")
    if inm is not None and _etag_matches(inm, etag):
        return Response(status_code=304, headers=headers)
    wanted = parse_range(request.headers.get("range"), size)
    if_range = request.headers.get("if-range")
    if if_range is not None and if_range.strip() != etag:
        wanted = None  # the client's partial copy is of another version: send it all
    if wanted == "unsatisfiable":
        shown = request.headers.get("range", "")
        shown = shown if len(shown) <= 80 else shown[:60] + "..."
        raise ApiError(416, f"range {shown!r} is outside the {size}-byte file",
                       headers={"Content-Range": f"bytes */{size}"})
    start, end, status = 0, size, 200
    if isinstance(wanted, tuple):
        start, end, status = wanted[0], wanted[1], 206
        headers["Content-Range"] = f"bytes {start}-{end - 1}/{size}"
    headers["Content-Length"] = str(end - start)
    if request.method == "HEAD":
        return Response(status_code=status, headers=headers, media_type=content_type)
    return StreamingResponse(blobs.read_range(key, start, end), status_code=status,
                             headers=headers, media_type=content_type)
