"""Writing and reading whole `.dgss` sequence streams (docs/stream.md): the header a player
needs (frames, frame rate, the renderer's settings, the capture light relighting divides by,
cameras, the byte range of every group) and one chunk per group of pictures."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from core.export.codec import GroupDecoder, StreamConfig
from core.export.container import (
    StreamError,
    pack_chunk,
    pack_file,
    pack_payload,
    read_header,
    unpack_chunk,
    unpack_payload,
)
from core.export.encode import encode_group
from core.export.splats import Splats

__all__ = ["StreamStats", "decode_group", "read_stream", "write_stream"]


@dataclass
class StreamStats:
    """What writing a stream cost."""

    bytes: int = 0
    """The file's size."""
    group_bytes: list[int] = field(default_factory=list)
    """Each group's chunk size (header included)."""
    encode_seconds: float = 0.0
    """Encoding and compression, every group."""
    frame_meta: list[dict] = field(default_factory=list)
    """Per frame: Gaussians, births, deaths and slots updated per attribute."""


def write_stream(path: str | os.PathLike[str], groups: list[list[Splats]], header: dict,
                 config: StreamConfig = StreamConfig(), *, sh_dim: int = 15) -> StreamStats:
    """Encode `groups` (each a key frame and its tracked frames) into the stream at `path`,
    atomically. `header` must name `frames` (one per frame, in order) and `fps`; its other
    keys (render settings, capture light, cameras, up axis) are passed through for players."""
    count = sum(len(g) for g in groups)
    if len(header.get("frames", ())) != count:
        raise ValueError(f"header: 'frames' must name the {count} frames of the groups")
    if not float(header.get("fps", 0)) > 0:
        raise ValueError(f"header: expected a frame rate 'fps' > 0, got {header.get('fps')!r}")
    stats, chunks, index, first = StreamStats(), [], [], 0
    start = time.perf_counter()
    for g, frames in enumerate(groups):
        meta, arrays = encode_group(frames, config, sh_dim=sh_dim, group=g,
                                    cameras=header.get("cameras"))
        chunk = pack_chunk(g, pack_payload(meta, arrays))
        chunks.append(chunk)
        index.append({"index": g, "first": first, "count": len(frames),
                      "key": header["frames"][first],
                      "gaussians": [m["gaussians"] for m in meta["frame_meta"]]})
        stats.frame_meta += meta["frame_meta"]
        stats.group_bytes.append(len(chunk))
        first += len(frames)
    stats.encode_seconds = time.perf_counter() - start
    data = pack_file({**header, "format": "dgs-stream", "sh_dim": sh_dim, "groups": index},
                     chunks)
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    stats.bytes = len(data)
    return stats


def decode_group(raw: bytes, group: int) -> Iterator[Splats]:
    """The frames of one group from its chunk bytes (StreamError when they are damaged)."""
    payload = unpack_payload(unpack_chunk(raw, group), f"group {group}")
    decoder = GroupDecoder.from_payload(payload)
    for _ in payload.meta["frame_meta"]:
        yield decoder.frame()


def read_stream(path: str | os.PathLike[str]) -> tuple[dict, Iterator[Splats]]:
    """(header, every frame in order) of the stream at `path`; StreamError names the first
    group that is truncated or corrupted."""
    raw = Path(path).read_bytes()
    try:
        header, data = read_header(raw)
    except StreamError as exc:
        raise StreamError(f"{path}: {exc}") from None

    def frames() -> Iterator[Splats]:
        for g in header["groups"]:
            start = data + int(g["offset"])
            chunk = raw[start:start + int(g["length"])]
            try:
                yield from decode_group(chunk, int(g["index"]))
            except StreamError as exc:
                raise StreamError(f"{path}: {exc}") from None

    return header, frames()
