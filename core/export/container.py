"""The byte layout of a `.dgss` sequence stream (docs/stream.md): a versioned header, then one
self-checking chunk per group of pictures, each seekable and range-requestable on its own.

    file    = "DGSS" u16 version u16 0 u32 header_length, header (UTF-8 JSON), chunk ...
    chunk   = "DGSG" u32 group u32 length u32 crc32, payload (zlib, `length` bytes)
    payload = u32 table_length, table (UTF-8 JSON: group metadata and sections), section bytes

The header's `groups` give each chunk's `offset` (from the end of the header) and `length`
(chunk header included), so a player fetches the header, then any group by one HTTP range.
A section is a little-endian typed array; `shuffle` ones are stored byte plane by byte plane
(all first bytes, then all second bytes, ...), which deflate compresses better. Torch-free.
"""

from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass

import numpy as np

__all__ = ["CHUNK_HEADER", "FILE_HEADER", "StreamError", "Payload", "VERSION", "pack_chunk",
           "pack_file", "pack_payload", "read_header", "unpack_chunk", "unpack_payload"]

VERSION = 1
FILE_MAGIC, CHUNK_MAGIC = b"DGSS", b"DGSG"
FILE_HEADER = 12
CHUNK_HEADER = 16
DTYPES = {"i8": "<i1", "u8": "<u1", "u16": "<u2", "u32": "<u4", "i16": "<i2", "i32": "<i4", "f32": "<f4"}
_NAMES = {np.dtype(v): k for k, v in DTYPES.items()}


class StreamError(ValueError):
    """A stream that cannot be read: what is wrong and where."""


@dataclass
class Payload:
    """A decoded chunk: its metadata and named arrays."""

    meta: dict
    arrays: dict[str, np.ndarray]

    def get(self, name: str) -> np.ndarray:
        if name not in self.arrays:
            raise StreamError(f"group {self.meta.get('group')}: section {name!r} is missing")
        return self.arrays[name]


def _shuffle(raw: bytes, itemsize: int) -> bytes:
    return np.frombuffer(raw, np.uint8).reshape(-1, itemsize).T.tobytes()


def _unshuffle(raw: bytes, itemsize: int) -> bytes:
    return np.frombuffer(raw, np.uint8).reshape(itemsize, -1).T.tobytes()


def pack_payload(meta: dict, arrays: dict[str, np.ndarray]) -> bytes:
    """Metadata and named arrays as one uncompressed payload (sections 4-byte aligned)."""
    sections, blobs, at = {}, [], 0
    for name, a in arrays.items():
        a = np.ascontiguousarray(a)
        dtype = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
        if dtype not in _NAMES:
            raise ValueError(f"arrays[{name!r}]: dtype {a.dtype} is not one of {sorted(DTYPES)}")
        raw = a.astype(DTYPES[_NAMES[dtype]]).tobytes()
        shuffle = a.dtype.itemsize > 1
        if shuffle:
            raw = _shuffle(raw, a.dtype.itemsize)
        sections[name] = {"offset": at, "dtype": _NAMES[dtype], "shape": list(a.shape),
                          "shuffle": shuffle}
        pad = (-len(raw)) % 4
        blobs.append(raw + b"\0" * pad)
        at += len(raw) + pad
    table = json.dumps({**meta, "sections": sections}, separators=(",", ":")).encode()
    table += b" " * ((-len(table)) % 4)
    return struct.pack("<I", len(table)) + table + b"".join(blobs)


def unpack_payload(raw: bytes, where: str) -> Payload:
    """The inverse of `pack_payload`; StreamError naming `where` when it does not add up."""
    if len(raw) < 4:
        raise StreamError(f"{where}: payload shorter than its table length")
    (n,) = struct.unpack_from("<I", raw)
    try:
        table = json.loads(raw[4:4 + n])
    except ValueError:
        raise StreamError(f"{where}: the section table is not JSON") from None
    base, arrays = 4 + n, {}
    for name, s in table.pop("sections", {}).items():
        dtype = np.dtype(DTYPES.get(s.get("dtype"), "V0"))
        count = int(np.prod(s["shape"], dtype=np.int64))
        start, size = base + int(s["offset"]), count * dtype.itemsize
        if dtype.itemsize == 0 or start + size > len(raw):
            raise StreamError(f"{where}: section {name!r} runs past the payload")
        chunk = raw[start:start + size]
        if s.get("shuffle"):
            chunk = _unshuffle(chunk, dtype.itemsize)
        arrays[name] = np.frombuffer(chunk, dtype).reshape(s["shape"])
    return Payload(table, arrays)


def pack_chunk(group: int, payload: bytes, level: int = 9) -> bytes:
    """One chunk: header and the zlib-compressed payload."""
    body = zlib.compress(payload, level)
    return CHUNK_MAGIC + struct.pack("<III", group, len(body), zlib.crc32(body)) + body


def unpack_chunk(raw: bytes, group: int) -> bytes:
    """The payload of group `group`'s chunk `raw`, checked: StreamError when it is truncated or
    corrupted (magic, group number, length, CRC-32, zlib)."""
    where = f"group {group}"
    if len(raw) < CHUNK_HEADER or raw[:4] != CHUNK_MAGIC:
        raise StreamError(f"{where}: no chunk header (truncated or not a stream)")
    index, length, crc = struct.unpack_from("<III", raw, 4)
    if index != group:
        raise StreamError(f"{where}: the chunk found there is group {index}")
    body = raw[CHUNK_HEADER:CHUNK_HEADER + length]
    if len(body) < length:
        raise StreamError(f"{where}: truncated ({len(body)} of {length} bytes)")
    if zlib.crc32(body) != crc:
        raise StreamError(f"{where}: corrupted (CRC-32 mismatch)")
    try:
        return zlib.decompress(body)
    except zlib.error as exc:
        raise StreamError(f"{where}: corrupted ({exc})") from None


def pack_file(header: dict, chunks: list[bytes]) -> bytes:
    """The whole stream: `header` gets each group's offset and length filled in."""
    at, groups = 0, []
    for g, chunk in zip(header["groups"], chunks):
        groups.append({**g, "offset": at, "length": len(chunk)})
        at += len(chunk)
    head = json.dumps({**header, "version": VERSION, "groups": groups, "data_bytes": at},
                      separators=(",", ":")).encode()
    return FILE_MAGIC + struct.pack("<HHI", VERSION, 0, len(head)) + head + b"".join(chunks)


def read_header(raw: bytes) -> tuple[dict, int]:
    """(header, where the data starts) from the first bytes of a stream."""
    if len(raw) < FILE_HEADER or raw[:4] != FILE_MAGIC:
        raise StreamError("not a dgs stream (no 'DGSS' magic)")
    version, _, n = struct.unpack_from("<HHI", raw, 4)
    if version != VERSION:
        raise StreamError(f"stream version {version}; this reads version {VERSION}")
    if len(raw) < FILE_HEADER + n:
        raise StreamError(f"header truncated ({len(raw) - FILE_HEADER} of {n} bytes)")
    try:
        header = json.loads(raw[FILE_HEADER:FILE_HEADER + n])
    except ValueError:
        raise StreamError("the header is not JSON") from None
    return header, FILE_HEADER + n
