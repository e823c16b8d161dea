"""Opaque cursors for listings. A cursor holds the sort key of the last item a page returned;
the next page starts strictly after it, so rows inserted meanwhile never shift a page (unlike
offsets) and every row is listed once."""

from __future__ import annotations

import base64
import datetime as dt
import json
from typing import Any

from sqlalchemy import Select, and_, or_

from service.errors import ApiError

__all__ = ["decode_cursor", "encode_cursor", "newest_first", "newest_page"]


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


def newest_first(query: Select, created_col, id_col, cursor: str | None, limit: int) -> Select:
    """`query` ordered newest first by (created_at, id), after `cursor`, `limit` + 1 rows (the
    extra row tells whether another page exists)."""
    if cursor:
        created, ident = decode_cursor(cursor, (dt.datetime, str))
        query = query.where(or_(created_col < created,
                                and_(created_col == created, id_col < ident)))
    return query.order_by(created_col.desc(), id_col.desc()).limit(limit + 1)


def newest_page(session, query: Select, created_col, id_col, cursor: str | None,
                limit: int) -> tuple[list, str | None]:
    """One page of `query`'s rows, newest first after `cursor`, and the cursor of the next page
    (None on the last)."""
    rows = list(session.scalars(newest_first(query, created_col, id_col, cursor, limit)))
    if len(rows) <= limit:
        return rows, None
    rows = rows[:limit]
    return rows, encode_cursor(rows[-1].created_at, rows[-1].id)
