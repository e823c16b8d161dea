"""The artifact store: a local folder by default, any S3-compatible store (boto3) in deployment.

Keys are relative, '/'-separated paths: captures/<id>/..., jobs/<id>/artifacts/...,
jobs/<id>/state/... (checkpoints of a running job), assets/<id>/<file>. A key that could leave
its folder (absolute, '..', backslash, NUL, empty parts) is refused before any I/O.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol
from urllib.parse import unquote, urlparse

__all__ = ["BlobInfo", "BlobStore", "LocalBlobStore", "S3BlobStore", "check_key", "open_store"]

CHUNK = 1 << 20


def check_key(key: str) -> str:
    """`key` if it is a safe relative path, else ValueError naming the problem."""
    if not isinstance(key, str) or not key:
        raise ValueError("key: expected a non-empty relative path")
    if key.startswith("/") or "\\" in key or "\x00" in key:
        raise ValueError(f"key: {key!r} must be a relative '/'-separated path")
    parts = key.split("/")
    if any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"key: {key!r} has an empty, '.' or '..' part")
    return key


def _write(dest: Path, fill: Callable[[Path], object]) -> None:
    """`fill` a new file beside `dest`, then rename it over `dest` (writes are atomic). The
    temporary has a name of its own, so two processes writing the same file (two jobs fetching
    one capture) never write into, or rename away, each other's."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(dir=dest.parent, prefix=f".{dest.name}.", suffix=".part")
    os.close(fd)
    try:
        fill(Path(name))
        os.replace(name, dest)
    except BaseException:
        Path(name).unlink(missing_ok=True)
        raise


@dataclass(frozen=True)
class BlobInfo:
    key: str
    size: int


class BlobStore(Protocol):
    """What the API and the workers need from an artifact store."""

    def put_file(self, key: str, path: Path) -> None: ...

    def get_file(self, key: str, dest: Path) -> None: ...

    def size(self, key: str) -> int | None: ...

    def read_range(self, key: str, start: int, end: int) -> Iterator[bytes]:
        """Bytes start..end-1 of the blob, in chunks."""
        ...

    def list(self, prefix: str) -> list[BlobInfo]: ...

    def delete_prefix(self, prefix: str) -> int: ...

    def local_path(self, key: str) -> Path | None:
        """The blob as a file on this machine when the store is a local folder, else None."""
        ...


class LocalBlobStore:
    """Blobs as files under `root` (writes are atomic: a temporary file, then a rename)."""

    def __init__(self, root: str | os.PathLike[str]):
        self.root = Path(root).resolve()

    def _path(self, key: str) -> Path:
        return self.root.joinpath(*check_key(key).split("/"))

    def put_file(self, key: str, path: Path) -> None:
        _write(self._path(key), lambda tmp: shutil.copyfile(path, tmp))

    def get_file(self, key: str, dest: Path) -> None:
        src = self._path(key)
        if not src.is_file():
            raise FileNotFoundError(f"artifact store: no blob {key!r}")
        _write(dest, lambda tmp: shutil.copyfile(src, tmp))

    def size(self, key: str) -> int | None:
        path = self._path(key)
        return path.stat().st_size if path.is_file() else None

    def read_range(self, key: str, start: int, end: int) -> Iterator[bytes]:
        with open(self._path(key), "rb") as f:
            f.seek(start)
            left = end - start
            while left > 0:
                chunk = f.read(min(CHUNK, left))
                if not chunk:
                    break
                left -= len(chunk)
                yield chunk

    def list(self, prefix: str) -> list[BlobInfo]:
        base = self._path(prefix.rstrip("/"))
        if not base.is_dir():
            return []
        out = []
        for path in sorted(base.rglob("*")):
            if path.is_file() and not path.name.endswith(".part"):
                out.append(BlobInfo(path.relative_to(self.root).as_posix(), path.stat().st_size))
        return out

    def delete_prefix(self, prefix: str) -> int:
        base = self._path(prefix.rstrip("/"))
        if base.is_file():
            base.unlink()
            return 1
        if not base.is_dir():
            return 0
        n = sum(1 for p in base.rglob("*") if p.is_file())
        shutil.rmtree(base)
        return n

    def local_path(self, key: str) -> Path | None:
        return self._path(key)


class S3BlobStore:
    """Blobs as objects `prefix/key` in `bucket` of an S3-compatible store."""

    def __init__(self, bucket: str, prefix: str = "", *, endpoint_url: str | None = None,
                 region: str | None = None, client=None):
        # lazy: only with S3 storage (boto3)
        import boto3
        from botocore.config import Config  # lazy: as boto3

        self.bucket, self.prefix = bucket, prefix.strip("/")
        self.client = client or boto3.client(
            "s3", endpoint_url=endpoint_url, region_name=region,
            config=Config(retries={"max_attempts": 5, "mode": "standard"}))

    def _name(self, key: str) -> str:
        key = check_key(key)
        return f"{self.prefix}/{key}" if self.prefix else key

    def _key(self, name: str) -> str:
        return name[len(self.prefix) + 1:] if self.prefix else name

    def put_file(self, key: str, path: Path) -> None:
        self.client.upload_file(str(path), self.bucket, self._name(key))

    def get_file(self, key: str, dest: Path) -> None:
        # lazy: only with S3 storage (boto3)
        from botocore.exceptions import ClientError

        name = self._name(key)
        try:
            _write(dest, lambda tmp: self.client.download_file(self.bucket, name, str(tmp)))
        except ClientError as exc:
            raise FileNotFoundError(f"artifact store: no blob {key!r} ({exc})") from None

    def size(self, key: str) -> int | None:
        # lazy: only with S3 storage (boto3)
        from botocore.exceptions import ClientError

        name = self._name(key)
        try:
            head = self.client.head_object(Bucket=self.bucket, Key=name)
        except ClientError:
            return None
        return int(head["ContentLength"])

    def read_range(self, key: str, start: int, end: int) -> Iterator[bytes]:
        if end <= start:
            return
        obj = self.client.get_object(Bucket=self.bucket, Key=self._name(key),
                                     Range=f"bytes={start}-{end - 1}")
        body = obj["Body"]
        try:
            yield from body.iter_chunks(CHUNK)
        finally:
            body.close()

    def list(self, prefix: str) -> list[BlobInfo]:
        base = self._name(prefix.rstrip("/")) + "/"
        out = []
        for page in self.client.get_paginator("list_objects_v2").paginate(
                Bucket=self.bucket, Prefix=base):
            out += [BlobInfo(self._key(o["Key"]), int(o["Size"])) for o in page.get("Contents", [])]
        return sorted(out, key=lambda b: b.key)

    def delete_prefix(self, prefix: str) -> int:
        blobs = self.list(prefix)
        single = self.size(prefix.rstrip("/"))
        names = [self._name(b.key) for b in blobs] + (
            [self._name(prefix.rstrip("/"))] if single is not None else [])
        for i in range(0, len(names), 1000):  # the S3 API deletes at most 1000 per request
            self.client.delete_objects(Bucket=self.bucket, Delete={
                "Objects": [{"Key": n} for n in names[i:i + 1000]], "Quiet": True})
        return len(names)

    def local_path(self, key: str) -> Path | None:
        return None


def open_store(url: str, *, endpoint_url: str | None = None,
               region: str | None = None) -> BlobStore:
    """`file:///abs/folder` or `s3://bucket/prefix`."""
    parsed = urlparse(url)
    if parsed.scheme == "file":
        return LocalBlobStore(unquote(parsed.path))
    if parsed.scheme == "s3":
        if not parsed.netloc:
            raise ValueError(f"storage_url: {url!r} names no bucket (s3://bucket/prefix)")
        return S3BlobStore(parsed.netloc, parsed.path.strip("/"), endpoint_url=endpoint_url,
                           region=region)
    raise ValueError(f"storage_url: expected file:///folder or s3://bucket/prefix, got {url!r}")
