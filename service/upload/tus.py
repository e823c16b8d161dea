"""tus 1.0.0 (core, creation, termination, checksum): headers, and the part files uploads are
written to.

A part file only ever grows at its end, one writer at a time: an exclusive lock on
<upload>.lock (flock, so it holds between the threads of one API process and between the
processes sharing the data folder). The job store's `uploads.offset` is the committed length:
bytes past it (a crash mid-write) are cut off before the next write. The SHA-256 of the
committed prefix is kept in memory between requests, so completing a 64 GiB file does not read
it again; after a restart (or when another process wrote last) the prefix is hashed once.
"""

from __future__ import annotations

import base64
import binascii
import fcntl
import hashlib
import os
import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from service.errors import ApiError

__all__ = [
    "ALGORITHMS",
    "EXTENSIONS",
    "HashCache",
    "PartLock",
    "PartWriter",
    "TUS_VERSION",
    "hash_prefix",
    "parse_checksum",
    "parse_length",
    "parse_metadata",
    "tus_headers",
]

TUS_VERSION = "1.0.0"
EXTENSIONS = ("creation", "termination", "checksum")
ALGORITHMS = {"sha1": hashlib.sha1, "sha256": hashlib.sha256, "md5": hashlib.md5}
OFFSET_TYPE = "application/offset+octet-stream"


def tus_headers(**extra: str | int) -> dict[str, str]:
    headers = {"Tus-Resumable": TUS_VERSION}
    headers.update({k.replace("_", "-"): str(v) for k, v in extra.items()})
    return headers


def parse_length(value: str | None, name: str) -> int:
    """A non-negative integer header (Upload-Length, Upload-Offset); 400 otherwise."""
    if value is None:
        raise ApiError(400, f"{name} header is required")
    if not (value.isascii() and value.isdigit()) or len(value) > 18:
        raise ApiError(400, f"{name}: expected a non-negative integer of at most 18 digits, "
                            f"got {value[:40]!r}")
    return int(value)


def parse_metadata(value: str | None) -> dict[str, str]:
    """Upload-Metadata: comma-separated `key base64(value)` pairs (the value may be absent)."""
    out: dict[str, str] = {}
    if not value or not value.strip():
        return out
    for item in value.split(","):
        parts = item.strip().split(" ")
        key = parts[0]
        if not key or len(parts) > 2 or key in out:
            raise ApiError(400, f"Upload-Metadata: malformed or repeated entry {item.strip()!r}")
        try:
            raw = base64.b64decode(parts[1], validate=True) if len(parts) == 2 else b""
            out[key] = raw.decode("utf-8")
        except (binascii.Error, UnicodeDecodeError):
            raise ApiError(400, f"Upload-Metadata: the value of {key!r} is not base64 of "
                                "UTF-8 text") from None
    return out


def parse_checksum(value: str | None) -> tuple[str, bytes] | None:
    """Upload-Checksum: `<algorithm> <base64 digest>`; None when absent."""
    if value is None:
        return None
    algo, _, encoded = value.strip().partition(" ")
    if algo not in ALGORITHMS:
        raise ApiError(400, f"Upload-Checksum: unsupported algorithm {algo!r}; supported: "
                            f"{', '.join(sorted(ALGORITHMS))}")
    try:
        digest = base64.b64decode(encoded.strip(), validate=True)
    except binascii.Error:
        raise ApiError(400, "Upload-Checksum: the digest is not base64") from None
    if len(digest) != ALGORITHMS[algo]().digest_size:
        raise ApiError(400, f"Upload-Checksum: a {algo} digest has "
                            f"{ALGORITHMS[algo]().digest_size} bytes, got {len(digest)}")
    return algo, digest


class PartLock:
    """Exclusive lock on one upload (context manager); ApiError 409 (retryable) when another
    request still writes to it after `timeout` seconds."""

    def __init__(self, path: Path, timeout: float = 10.0):
        self.path, self.timeout = path, timeout
        self.fd: int | None = None

    def acquire(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        deadline = time.monotonic() + self.timeout
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                self.fd = fd
                return
            except BlockingIOError:
                if time.monotonic() > deadline:
                    os.close(fd)
                    raise ApiError(409, "another request is writing to this upload; retry when "
                                        "it has ended (HEAD gives the offset)",
                                   retryable=True) from None
                time.sleep(0.05)

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)  # closing the descriptor releases the flock
            self.fd = None


def hash_prefix(path: Path, length: int):
    """SHA-256 object over the first `length` bytes of `path`."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        left = length
        while left > 0:
            chunk = f.read(min(4 << 20, left))
            if not chunk:
                raise ApiError(409, f"the upload's data ends before its offset {length}; "
                                    "terminate it and upload the file again")
            h.update(chunk)
            left -= len(chunk)
    return h


class HashCache:
    """upload id -> (offset, SHA-256 of the first `offset` bytes), most recent uploads only."""

    def __init__(self, size: int = 256):
        self.size = size
        self._items: OrderedDict[str, tuple[int, object]] = OrderedDict()
        self._lock = threading.Lock()

    def take(self, upload_id: str, offset: int, part: Path):
        """A hash of the part's first `offset` bytes (from memory when it is current)."""
        with self._lock:
            item = self._items.pop(upload_id, None)
        if item is not None and item[0] == offset:
            return item[1]
        return hash_prefix(part, offset)

    def keep(self, upload_id: str, offset: int, h) -> None:
        with self._lock:
            self._items[upload_id] = (offset, h)
            while len(self._items) > self.size:
                self._items.popitem(last=False)

    def drop(self, upload_id: str) -> None:
        with self._lock:
            self._items.pop(upload_id, None)


_HASHER = ThreadPoolExecutor(max_workers=4, thread_name_prefix="dgs-upload-hash")
"""Hashes upload blocks beside their writes (PartWriter.write); a thread each for up to four
uploads at once, more wait their turn."""


class PartWriter:
    """Appends a request's bytes to a part file from `offset` (bytes past it are cut off first),
    hashing them into `sha` (the whole file's SHA-256) and `check` (this request's checksum).

    The event loop `add`s what arrives and `take`s a block when enough has gathered; a worker
    thread `write`s and hashes that block (both release the GIL) while the loop goes on
    receiving the next, one block in flight at a time. The other methods block: call them in a
    worker thread with no block in flight."""

    def __init__(self, path: Path, offset: int, sha, check=None):
        self.path, self.start, self.offset = path, offset, offset
        self.sha, self.check = sha, check
        self.buf: list[bytes] = []
        self.buffered = 0
        """Bytes in `buf` (the chunks as they arrived: gathered by one writev, never copied)."""
        self.inflight = 0
        """Bytes taken from the buffer and not yet written."""
        self.synced = offset
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o600)
        self.rewind(offset)

    @property
    def received(self) -> int:
        """Bytes of this request so far (written, in flight and buffered)."""
        return self.offset + self.inflight + self.buffered - self.start

    def add(self, chunk: bytes) -> None:
        if chunk:
            self.buf.append(chunk)
            self.buffered += len(chunk)

    def take(self) -> list[bytes]:
        """The buffered chunks, handed over for `write`."""
        data, self.buf = self.buf, []
        self.inflight += self.buffered
        self.buffered = 0
        return data

    def write(self, data: list[bytes]) -> None:
        """Append and hash chunks from `take`: the hashes run in a helper thread while this one
        writes (both release the GIL), so a block costs the longer of the two, not the sum."""
        size = sum(len(c) for c in data)
        try:
            hashed = _HASHER.submit(self._hash, data)
            try:
                self._writev([memoryview(c) for c in data if len(c)])
            finally:
                hashed.result()  # also when the write failed: nothing may hash behind our back
            self.offset += size
        finally:
            self.inflight -= size

    def _hash(self, data: list[bytes]) -> None:
        for chunk in data:
            self.sha.update(chunk)
            if self.check is not None:
                self.check.update(chunk)

    def _writev(self, views: list[memoryview]) -> None:
        while views:  # writev may write less than asked (a signal, a full disk)
            n = os.writev(self.fd, views[:1024])
            if n == 0:
                raise OSError(f"{self.path}: the file system took no bytes")
            while views and n >= len(views[0]):
                n -= len(views[0])
                views.pop(0)
            if n:
                views[0] = views[0][n:]

    def flush(self) -> None:
        if self.buf:
            self.write(self.take())

    def sync_to(self, offset: int) -> None:
        """fsync, for bytes already written up to `offset` (blocks may be written meanwhile:
        they are past it); `synced` becomes `offset`."""
        os.fsync(self.fd)
        self.synced = max(self.synced, offset)

    def sync(self) -> int:
        """Flush and fsync; the returned offset is durable."""
        self.flush()
        self.sync_to(self.offset)
        return self.offset

    def rewind(self, offset: int) -> None:
        """Drop everything past `offset` (a failed checksum, an aborted request)."""
        self.buf.clear()
        self.buffered = 0
        os.ftruncate(self.fd, offset)
        os.lseek(self.fd, offset, os.SEEK_SET)
        self.offset = offset

    def close(self) -> None:
        os.close(self.fd)
