"""A zip of many blobs written while it is sent (NodeODM's all.zip): members stored, not
compressed (splats, PNGs and EXRs barely compress), ZIP64 so any size works, data descriptors
so nothing is seeked. Memory stays at one chunk whatever the total."""

from __future__ import annotations

import datetime as dt
import io
import zipfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from worker.blobs import BlobStore

__all__ = ["ZipEntry", "zip_stream"]


@dataclass(frozen=True)
class ZipEntry:
    name: str
    key: str
    size: int
    modified: dt.datetime


class _Sink(io.RawIOBase):
    """A write-only, unseekable file whose bytes the generator hands on."""

    def __init__(self) -> None:
        self.chunks: list[bytes] = []

    def writable(self) -> bool:
        return True

    def write(self, data) -> int:
        self.chunks.append(bytes(data))
        return len(data)

    def tell(self) -> int:
        raise OSError("unseekable")

    def drain(self) -> Iterator[bytes]:
        chunks, self.chunks = self.chunks, []
        yield from chunks


def zip_stream(blobs: BlobStore, entries: Iterable[ZipEntry]) -> Iterator[bytes]:
    sink = _Sink()
    with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for entry in entries:
            when = entry.modified.astimezone(dt.UTC)
            info = zipfile.ZipInfo(entry.name, date_time=(max(when.year, 1980), when.month,
                                                          when.day, when.hour, when.minute,
                                                          when.second))
            info.compress_type = zipfile.ZIP_STORED
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as member:
                for chunk in blobs.read_range(entry.key, 0, entry.size):
                    member.write(chunk)
                    yield from sink.drain()
            yield from sink.drain()
    yield from sink.drain()
