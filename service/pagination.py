"""Opaque cursors for listings. A cursor holds the sort key of the last item a page returned;
the next page starts strictly after it, so rows inserted meanwhile never shift a page (unlike
offsets) and every row is listed once."""

from __future__ import annotations

import base64
import datetime as dt
import json
from typing import Any

from service.errors import ApiError
from worker.api_queries import Key

__all__ = ["after", "decode_cursor", "encode_cursor", "next_cursor"]


def encode_cursor(*key: Any) -> str:
    values = [v.isoformat() if isinstance(v, dt.datetime) else v for v in key]
    return base64.urlsafe_b64encode(json.dumps(values).encode()).decode().rstrip("=")


def decode_cursor(cursor: str, types: tuple[type, ...]) -> list[Any]:
    """The key a cursor holds, checked against `types` (datetime, str or int per field)."""
    try:
        raw = json.loads(base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)))
        if not isinstance(raw, list) or len(raw) != len(types):
            raise ValueError
        out: list[Any] = []
        for value, kind in zip(raw, types, strict=True):
            if kind is dt.datetime:
                value = dt.datetime.fromisoformat(value)
                if value.tzinfo is None:
                    raise ValueError
            elif not isinstance(value, kind) or isinstance(value, bool):
                raise ValueError
            out.append(value)
        return out
    except (ValueError, TypeError, UnicodeDecodeError):
        raise ApiError(400, "cursor: not a cursor this listing returned; start without one",
                       details=[{"path": "cursor", "message": "invalid cursor"}]) from None


def after(cursor: str | None) -> Key | None:
    """The key a listing's cursor holds (None: the first page); 400 for what no listing
    returned."""
    if not cursor:
        return None
    created, ident = decode_cursor(cursor, (dt.datetime, str))
    return created, ident


def next_cursor(last: Key | None) -> str | None:
    """The cursor of the page after the one that ended at `last` (None: it was the last)."""
    return None if last is None else encode_cursor(*last)

