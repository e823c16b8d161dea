"""One-request bodies: spooling a request body to disk under a byte limit, and unpacking a zip
archive into a capture's staging folder without trusting anything it says.

Refused before a byte is extracted: absolute member names, '..', backslashes, control
characters, symlinks and other special files, encrypted members, duplicate names, more members
than `max_archive_members`, declared sizes over the per-file or per-capture limits, and members
whose compression ratio passes `max_archive_ratio` (zip bombs). Extraction still counts the
bytes it writes, since a member's header can lie.
"""

from __future__ import annotations

import hashlib
import lzma
import shutil
import stat
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

from fastapi import Request
from starlette.concurrency import run_in_threadpool as run

from service.body import content_length
from service.errors import ApiError
from service.settings import ServiceSettings
from service.upload.manifest import check_manifest, path_problem

__all__ = ["Member", "extract", "inspect_zip", "spool"]

CHUNK = 1 << 20
RATIO_FLOOR = 1 << 20
"""Members smaller than this are not held to the ratio limit (a tiny JSON compresses well)."""


async def spool(request: Request, dest: Path, limit: int, what: str) -> tuple[int, str]:
    """Write the request body to `dest`, refusing (413) as soon as it passes `limit` bytes;
    returns (size, sha256). `dest` is removed on any failure."""
    declared = content_length(request)
    if declared is not None and declared > limit:
        raise ApiError(413, f"{what} is {declared} bytes; the limit is {limit}")
    sha, size, buf = hashlib.sha256(), 0, bytearray()
    f = await run(open, dest, "wb")

    def write(data: bytes) -> None:
        f.write(data)
        sha.update(data)

    try:
        async for chunk in request.stream():
            size += len(chunk)
            if size > limit:
                raise ApiError(413, f"{what} passes the limit of {limit} bytes")
            buf += chunk
            if len(buf) >= CHUNK:
                data, buf = bytes(buf), bytearray()
                await run(write, data)
        await run(write, bytes(buf))
        await run(f.close)
    except BaseException:
        await run(f.close)
        dest.unlink(missing_ok=True)
        raise
    return size, sha.hexdigest()


@dataclass(frozen=True)
class Member:
    info: zipfile.ZipInfo
    path: str
    """Where it goes in the capture (a common top-level folder removed)."""


def _invalid(message: str, name: str | None = None) -> ApiError:
    details = [{"path": name, "message": message}] if name is not None else []
    return ApiError(422, f"archive: {name + ': ' if name else ''}{message}",
                    code="invalid_archive", details=details)


def _check_member(info: zipfile.ZipInfo, settings: ServiceSettings) -> None:
    name = info.filename
    problem = path_problem(name.rstrip("/") if info.is_dir() else name, settings.max_path_bytes)
    if problem is not None:
        raise _invalid(f"member name {problem}", repr(name))
    kind = stat.S_IFMT(info.external_attr >> 16)  # 0 when the archiver recorded no type
    if kind and kind not in (stat.S_IFREG, stat.S_IFDIR):
        raise _invalid("is a symlink or special file; only regular files are accepted", name)
    if info.flag_bits & 0x1:
        raise _invalid("is encrypted", name)
    if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2,
                                  zipfile.ZIP_LZMA):
        raise _invalid(f"uses an unsupported compression method {info.compress_type}", name)
    if info.file_size > RATIO_FLOOR and \
            info.file_size > settings.max_archive_ratio * max(info.compress_size, 1):
        raise _invalid(f"expands {info.file_size / max(info.compress_size, 1):.0f} times "
                       f"(limit {settings.max_archive_ratio:.0f}); refusing a possible zip bomb",
                       name)


def _strip_top(names: list[str]) -> int:
    """Length of a single top-level folder every member is in (a zipped folder), else 0."""
    tops = {n.split("/", 1)[0] for n in names}
    if len(tops) == 1 and all("/" in n for n in names):
        return len(tops.pop()) + 1
    return 0


def inspect_zip(path: Path, fmt: str, settings: ServiceSettings) -> list[Member]:
    """The archive's files, checked (ApiError 4xx otherwise); nothing is extracted."""
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError):
        raise _invalid("the body is not a zip archive") from None
    with zf:
        infos = zf.infolist()
    if len(infos) > settings.max_archive_members:
        raise ApiError(413, f"archive has {len(infos)} members; the limit is "
                            f"{settings.max_archive_members}")
    files = []
    for info in infos:
        _check_member(info, settings)
        if not info.is_dir():
            files.append(info)
    if not files:
        raise _invalid("it holds no files")
    cut = _strip_top([i.filename for i in files])
    members = [Member(i, i.filename[cut:]) for i in files]
    total = check_manifest(((m.path, m.info.file_size) for m in members), fmt, settings)
    if total > settings.max_archive_expanded_bytes:
        raise ApiError(413, f"archive expands to {total} bytes; the limit is "
                            f"{settings.max_archive_expanded_bytes} (upload larger captures "
                            "file by file with tus)")
    free = shutil.disk_usage(path.parent).free
    if total > free:
        raise ApiError(507, f"archive expands to {total} bytes; the server has {free} free",
                       code="insufficient_storage", retryable=True)
    return members


def _copy(src, dest: Path, limit: int, name: str) -> tuple[int, str]:
    sha, size = hashlib.sha256(), 0
    with open(dest, "wb") as out:
        while chunk := src.read(CHUNK):
            size += len(chunk)
            if size > limit:
                raise _invalid("holds more bytes than its header declares", name)
            out.write(chunk)
            sha.update(chunk)
    return size, sha.hexdigest()


def extract(archive: Path, members: list[Member], dest: Path) -> list[dict]:
    """Extract `members` under `dest` (removed again on failure); returns the manifest."""
    manifest = []
    try:
        with zipfile.ZipFile(archive) as zf:
            for m in members:
                target = dest.joinpath(*m.path.split("/"))
                target.parent.mkdir(parents=True, exist_ok=True)
                with zf.open(m.info) as src:
                    size, digest = _copy(src, target, m.info.file_size, m.info.filename)
                manifest.append({"path": m.path, "size": size, "sha256": digest})
    except (zipfile.BadZipFile, EOFError, zlib.error, lzma.LZMAError,
            NotImplementedError) as exc:
        shutil.rmtree(dest, ignore_errors=True)
        raise _invalid(f"corrupt archive: {exc}") from None
    except OSError as exc:
        shutil.rmtree(dest, ignore_errors=True)
        if exc.errno is not None:  # the disk, not the archive
            raise
        raise _invalid(f"corrupt archive: {exc}") from None
    except BaseException:
        shutil.rmtree(dest, ignore_errors=True)
        raise
    return manifest
