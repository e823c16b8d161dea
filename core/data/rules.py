"""The rules every name, path and metadata file a client sends is held to, stated once: the
API (service.schemas, service.upload.manifest), capture.json (core.data.schema) and every
importer (core.data.importers) use these and no copy of them.

- A **display name** (a capture's or a job's `name`) is printable text: `unprintable_at`.
- A **frame or camera id** is a file name: `valid_name` (letters, digits, `_`, `.`, `-`, at
  most `MAX_NAME_CHARS`). An importer derives ids from its source's names (a camera folder,
  a file path, a CSV cell) with `safe_name`, after `name_problem` has refused what cannot
  become one: a name outside printable ASCII is refused, never transliterated, so two
  cameras cannot silently become one id and an id always says which source name it is.
- A **path** a client names (a manifest entry, an archive member, a file an importer's
  metadata points at) is relative, POSIX, and cannot leave its folder: `path_problem`.
- A **metadata file** parsed whole (JSON, CSV, npz) is bounded by its size before it is read
  and by its count of JSON values before it is parsed: `read_bounded`, `json_values_problem`.

Messages never contain a server path: callers name the file the way their user knows it.
"""

from __future__ import annotations

import functools
import re
from pathlib import Path

__all__ = [
    "MAX_JSON_VALUES",
    "MAX_METADATA_BYTES",
    "MAX_NAME_CHARS",
    "json_values_problem",
    "name_problem",
    "path_problem",
    "read_bounded",
    "safe_name",
    "unprintable_at",
    "valid_name",
]

MAX_NAME_CHARS = 200
"""Longest frame or camera id: it is a file name (255 bytes on common file systems) with a
folder's worth of room for an extension."""
MAX_METADATA_BYTES = 64 << 20
"""Largest metadata file parsed whole (capture.json, transforms.json, train_meta.json,
calibration.csv, cameras.npz, COLMAP's cameras file): checked from its size before a byte is
read. The largest real one we know, a Panoptic sequence's train_meta.json, is 2 MB."""
MAX_JSON_VALUES = 2_000_000
"""Most JSON values a metadata file may hold (about 74,000 Panoptic views or 100,000
transforms.json entries), counted at memchr speed before it is parsed: parsing holds about 40
bytes of memory and 1 us a value (a 98 MB file of 10^6 frames held 2.27 GB for 74 s)."""
MAX_PART_BYTES = 255  # a file name on every common file system

_ID_CHARS = r"A-Za-z0-9_.\-"
_NAME_RE = re.compile(rf"^[A-Za-z0-9_][{_ID_CHARS}]*$")
_NOT_ID_CHAR = re.compile(rf"[^{_ID_CHARS}]")
_GOOD_NAME = re.compile(r"[ -~]*[A-Za-z0-9][ -~]*")
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
_DRIVE = re.compile(r"^[A-Za-z]:")


def valid_name(name: object) -> bool:
    """True when ``name`` can be used as a frame or camera id (a single safe path component)."""
    return (isinstance(name, str) and len(name) <= MAX_NAME_CHARS
            and bool(_NAME_RE.match(name)) and name not in (".", ".."))


def unprintable_at(text: str) -> int | None:
    """Index of the first character of `text` that is not printable (str.isprintable: control,
    format and separator characters but the space), or None: the API's rule for names."""
    return next((i for i, c in enumerate(text) if not c.isprintable()), None)


def name_problem(text: object) -> str | None:
    """Why `text`, a name in a source file, cannot become a frame or camera id (None when it
    can): it must be printable ASCII, 1 to `MAX_NAME_CHARS` characters, and hold a letter or
    a digit. Other printable ASCII (a space, '/') becomes '_' in the id (`safe_name`)."""
    if isinstance(text, str) and len(text) <= MAX_NAME_CHARS and _GOOD_NAME.fullmatch(text):
        return None  # the common case, at regex speed (a source names every view)
    if not isinstance(text, str):
        return f"must be text, got {type(text).__name__}"
    if not text:
        return "is empty"
    if len(text) > MAX_NAME_CHARS:
        return f"is {len(text)} characters long; an id may have {MAX_NAME_CHARS}"
    at = unprintable_at(text)
    if at is not None:
        return f"character {at} is U+{ord(text[at]):04X}, which is not printable"
    at = next((i for i, c in enumerate(text) if not c.isascii()), None)
    if at is not None:
        return (f"character {at} ({text[at]!r}, U+{ord(text[at]):04X}) is outside ASCII; "
                "frame and camera ids are file names of A-Z a-z 0-9 _ . - : rename it")
    if not any(c.isalnum() for c in text):
        return "has no letter or digit to make an id of"
    return None


@functools.lru_cache(maxsize=1 << 16)  # a source names each camera and frame once a view
def safe_name(text: str) -> str:
    """The frame or camera id of a source name that `name_problem` accepts: each character
    that an id cannot hold becomes '_', leading '_', '.', '-' and trailing '.' are dropped.
    ValueError when `text` breaks `name_problem` (callers check first, naming the field)."""
    problem = name_problem(text)
    if problem is not None:
        raise ValueError(f"name {text!r} {problem}")
    out = _NOT_ID_CHAR.sub("_", text).strip(".").lstrip("_.-")
    if not valid_name(out):  # `name_problem` leaves a letter or digit, so never
        raise ValueError(f"name {text!r} gives no usable id ({out!r})")
    return out


def path_problem(path: object, max_bytes: int = 1024) -> str | None:
    """What is wrong with `path` as a file inside a capture, or None when it is safe: a
    relative POSIX path without control characters, backslashes, or empty, '.' or '..'
    components."""
    if not isinstance(path, str) or not path:
        return "empty path"
    if _CONTROL.search(path):
        return "contains a control character"
    if "\\" in path:
        return "contains a backslash; use '/' between folders"
    if path.startswith("/") or _DRIVE.match(path):
        return "is absolute; paths are relative to the capture folder"
    if len(path.encode("utf-8", "surrogatepass")) > max_bytes:
        return f"is longer than {max_bytes} bytes"
    try:
        path.encode("utf-8")
    except UnicodeEncodeError:
        return "is not valid UTF-8"
    for part in path.split("/"):
        if part in ("", ".", ".."):
            return "has an empty, '.' or '..' component"
        if len(part.encode("utf-8")) > MAX_PART_BYTES:
            return f"has a component longer than {MAX_PART_BYTES} bytes"
    return None


def read_bounded(path: Path, limit: int = MAX_METADATA_BYTES) -> bytes:
    """The bytes of `path`, refused (ValueError saying why, without the path) when its size
    passes `limit`, checked before a byte is read."""
    try:
        size = path.stat().st_size
        if size > limit:
            raise ValueError(f"is {size} bytes; a metadata file may have {limit} (it is "
                             "read whole, in memory)")
        with open(path, "rb") as f:
            data = f.read(limit + 1)
    except OSError as exc:
        raise ValueError(f"cannot read: {exc.strerror or type(exc).__name__}") from None
    if len(data) > limit:  # it grew since stat
        raise ValueError(f"passes {limit} bytes; a metadata file may have {limit}")
    return data


def json_values_problem(data: bytes, limit: int = MAX_JSON_VALUES) -> str | None:
    """Why `data` holds too many JSON values to parse (None when it may be parsed). Every value
    but a container's first follows a comma, so commas and openings bound the values; counted
    at memchr speed (a string's commas count too: the bound errs on the safe side)."""
    values = data.count(b",") + data.count(b"[") + data.count(b"{")
    if values > limit:
        return (f"holds about {values} JSON values; a metadata file may hold {limit} (about "
                "74,000 Panoptic views or 100,000 transforms.json entries)")
    return None
