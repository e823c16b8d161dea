"""service.upload.tus.PartWriter: the block pipeline's bookkeeping (what is buffered, in flight and
written), partial writes, and rewinds."""

from __future__ import annotations

import hashlib
import os

import pytest

from service.upload.tus import PartWriter


def test_chunks_are_written_in_order_hashed_and_counted(tmp_path):
    part = tmp_path / "part"
    part.write_bytes(b"kept" + b"garbage past the offset")
    sha = hashlib.sha256(b"kept")
    w = PartWriter(part, 4, sha, hashlib.sha1())
    chunks = [b"a" * 70_000, b"", b"b" * 5, os.urandom(300_000)]
    for c in chunks[:2]:
        w.add(c)
    assert w.received == 70_000 and w.buffered == 70_000
    block = w.take()
    assert w.received == 70_000 and w.inflight == 70_000 and w.buffered == 0
    for c in chunks[2:]:
        w.add(c)  # arrives while the block is written
    w.write(block)
    assert w.inflight == 0 and w.offset == 70_004
    assert w.sync() == 4 + sum(map(len, chunks)) and w.synced == w.offset
    w.close()
    body = b"".join(chunks)
    assert part.read_bytes() == b"kept" + body
    assert sha.hexdigest() == hashlib.sha256(b"kept" + body).hexdigest()
    assert w.check.hexdigest() == hashlib.sha1(body).hexdigest()
    assert w.received == len(body)


def test_a_short_writev_is_continued(tmp_path, monkeypatch):
    """writev may take fewer bytes than asked: the rest goes in the next call."""
    real = os.writev

    def short(fd, buffers):
        first = bytes(buffers[0])
        return real(fd, [first[: max(1, len(first) // 3)]])

    monkeypatch.setattr(os, "writev", short)
    part = tmp_path / "part"
    w = PartWriter(part, 0, hashlib.sha256())
    data = [os.urandom(1000), os.urandom(7), os.urandom(4096)]
    for c in data:
        w.add(c)
    w.sync()
    w.close()
    assert part.read_bytes() == b"".join(data)


def test_a_file_system_that_takes_nothing_is_an_error(tmp_path, monkeypatch):
    monkeypatch.setattr(os, "writev", lambda fd, buffers: 0)
    w = PartWriter(tmp_path / "part", 0, hashlib.sha256())
    w.add(b"x" * 10)
    with pytest.raises(OSError, match="took no bytes"):
        w.flush()
    assert w.inflight == 0  # the bookkeeping is back even though the write failed
    w.close()


def test_rewind_drops_what_passed_the_offset(tmp_path):
    part = tmp_path / "part"
    w = PartWriter(part, 0, hashlib.sha256())
    w.add(b"0123456789")
    w.sync()
    w.add(b"unsynced")
    w.flush()
    w.rewind(w.synced)
    w.add(b"AB")
    w.sync()
    w.close()
    assert part.read_bytes() == b"0123456789AB"
