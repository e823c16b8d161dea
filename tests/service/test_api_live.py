"""Against a real uvicorn server on a loopback port: a capture uploaded with the standard tus
client (tuspy), interrupted and resumed, arrives byte-exact and commits; a connection dropped
mid-body keeps what arrived; server-sent events arrive while a job runs and resume after a
reconnect."""

from __future__ import annotations

import hashlib
import io
import socket
import struct
import threading
import time
import zlib
from pathlib import Path

import httpx
import pytest
import uvicorn
from service_harness import TUS, capture_files, make_settings, manifest_of, metadata
from test_api_jobs import parse_sse
from tusclient import client as tus_client
from tusclient.storage.filestorage import FileStorage

from service.app import create_app
from service.routers import uploads as uploads_router

BIG = "images/000000/cam00.png"
MiB = 1 << 20
pytestmark = pytest.mark.timeout(180)


def padded_png(png: bytes, extra: int) -> bytes:
    """The same image with an `extra`-byte private ancillary chunk before IEND: a valid PNG
    (decoders skip unknown ancillary chunks) that makes a multi-megabyte upload."""
    data = bytes(i % 251 for i in range(extra))
    chunk = struct.pack(">I", len(data)) + b"dgSp" + data
    chunk += struct.pack(">I", zlib.crc32(b"dgSp" + data) & 0xFFFFFFFF)
    end = png.rindex(b"IEND") - 4
    return png[:end] + chunk + png[end:]


@pytest.fixture
def server(tmp_path: Path):
    app = create_app(make_settings(tmp_path / "data", sse_keepalive_seconds=0.2))
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "server did not start"
        time.sleep(0.02)
    yield f"http://127.0.0.1:{sock.getsockname()[1]}", app.state.services
    server.should_exit = True
    thread.join(timeout=10)
    sock.close()


def test_tuspy_upload_interrupted_and_resumed_is_byte_exact(server, synth_capture, tmp_path):
    base, services = server
    files = capture_files(synth_capture)
    files[BIG] = padded_png(files[BIG], 6 * MiB)
    capture = httpx.post(f"{base}/v1/captures", json={
        "format": "canonical", "manifest": manifest_of(files)}).json()
    tus = tus_client.TusClient(f"{base}/v1/uploads")
    for path, data in files.items():
        if path != BIG:
            tus.uploader(file_stream=io.BytesIO(data), chunk_size=MiB,
                         metadata={"capture": capture["id"], "path": path}).upload()
    big = tmp_path / "big.png"
    big.write_bytes(files[BIG])
    storage = FileStorage(str(tmp_path / "tus-urls.json"))

    def uploader():
        return tus.uploader(str(big), chunk_size=MiB, store_url=True, url_storage=storage,
                            metadata={"capture": capture["id"], "path": BIG})

    first = uploader()
    first.upload(stop_at=3 * MiB)  # the client stops (a laptop lid closed)
    assert first.offset == 3 * MiB
    state = httpx.get(f"{base}/v1/captures/{capture['id']}").json()["files"]
    assert state["missing_paths"] == [BIG]
    second = uploader()  # a new process: the URL comes from the client's storage
    assert second.url == first.url and second.offset == 3 * MiB  # resumed, not restarted
    second.upload()
    staged = services.staging.file(capture["id"], BIG)
    assert hashlib.sha256(staged.read_bytes()).digest() == hashlib.sha256(files[BIG]).digest()
    r = httpx.post(f"{base}/v1/captures/{capture['id']}/commit", timeout=60)
    assert r.status_code == 200, r.text
    assert r.json()["summary"]["cameras"] == 8
    stored = services.blobs.local_path(f"captures/{capture['id']}/{BIG}")
    assert stored.read_bytes() == files[BIG]


def test_a_dropped_connection_keeps_what_arrived(server, tmp_path):
    base, services = server
    data = bytes(i % 253 for i in range(4 * MiB))
    files = {"capture.json": b"{}", "images/000000/a.png": data}
    capture = httpx.post(f"{base}/v1/captures", json={
        "format": "canonical", "manifest": manifest_of(files)}).json()
    path = httpx.post(f"{base}/v1/uploads", headers={
        **TUS, "Upload-Length": str(len(data)),
        "Upload-Metadata": metadata(capture=capture["id"], path="images/000000/a.png")},
    ).headers["Location"].removeprefix("/")  # a relative reference
    url = f"{base}/{path}"
    port = int(base.rsplit(":", 1)[1])
    sent = 2 * MiB + 12345
    with socket.create_connection(("127.0.0.1", port)) as conn:
        conn.sendall((f"PATCH /{path} HTTP/1.1\r\nHost: 127.0.0.1\r\nTus-Resumable: 1.0.0\r\n"
                      f"Upload-Offset: 0\r\nContent-Type: application/offset+octet-stream\r\n"
                      f"Content-Length: {len(data)}\r\n\r\n").encode() + data[:sent])
        time.sleep(0.5)  # the server has read what was sent; then the connection drops
    deadline = time.monotonic() + 60  # a bound for a stuck server, not a timing: a busy one
    offset = 0
    while time.monotonic() < deadline:
        offset = int(httpx.head(url, headers=TUS).headers["Upload-Offset"])
        if offset:
            break
        time.sleep(0.1)
    assert 0 < offset <= sent  # what arrived was kept
    tus = tus_client.TusClient(f"{base}/v1/uploads")
    resumed = tus.uploader(file_stream=io.BytesIO(data), url=url, chunk_size=MiB)
    assert resumed.offset == offset
    resumed.upload()
    assert services.staging.file(capture["id"], "images/000000/a.png").read_bytes() == data


def _patch_head(path: str, offset: int, length: int) -> bytes:
    return (f"PATCH {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nTus-Resumable: 1.0.0\r\n"
            f"Upload-Offset: {offset}\r\nContent-Type: application/offset+octet-stream\r\n"
            f"Content-Length: {length}\r\n\r\n").encode()


def _response(conn: socket.socket) -> tuple[int, bytes]:
    """(status, body) of one HTTP/1.1 response with a Content-Length."""
    data = b""
    while b"\r\n\r\n" not in data:
        data += conn.recv(4096)
    head, body = data.split(b"\r\n\r\n", 1)
    length = next((int(line.split(b":", 1)[1]) for line in head.split(b"\r\n")
                   if line.lower().startswith(b"content-length:")), 0)
    while len(body) < length:
        body += conn.recv(4096)
    return int(head.split(b" ", 2)[1]), body


def test_concurrent_patches_do_not_interleave(server, monkeypatch):
    """A client retries while its first request still streams: the second request waits for
    the first, then is told the upload moved on (409: it is complete); the file is intact.
    The order is made by events, not sleeps: the server's upload lock says when the first
    request holds it and when the retry is waiting for it."""
    base, services = server
    held, waiting = threading.Event(), threading.Event()

    class WatchedLock(uploads_router.PartLock):
        # A slow machine must not turn the wait into the lock's own 409 ("another request is
        # writing to this upload") after its 10 s.
        def __init__(self, path, timeout: float = 10.0):
            super().__init__(path, timeout=600.0)

        def acquire(self) -> None:
            if held.is_set():
                waiting.set()  # the first request holds the lock: this one waits for it
            super().acquire()
            held.set()

    monkeypatch.setattr(uploads_router, "PartLock", WatchedLock)
    data = bytes(i % 241 for i in range(2 * MiB))
    files = {"capture.json": b"{}", "images/000000/a.png": data}
    capture = httpx.post(f"{base}/v1/captures", json={
        "format": "canonical", "manifest": manifest_of(files)}).json()
    url = httpx.post(f"{base}/v1/uploads", headers={
        **TUS, "Upload-Length": str(len(data)),
        "Upload-Metadata": metadata(capture=capture["id"], path="images/000000/a.png")},
    ).headers["Location"]
    path, port = url, int(base.rsplit(":", 1)[1])  # Location is relative
    second: list[tuple[int, bytes]] = []

    def retry():
        with socket.create_connection(("127.0.0.1", port)) as conn:
            conn.sendall(_patch_head(path, 0, len(data)) + data)
            second.append(_response(conn))

    with socket.create_connection(("127.0.0.1", port)) as first:
        first.sendall(_patch_head(path, 0, len(data)) + data[:MiB])
        assert held.wait(60), "the first PATCH never took the upload's lock"
        thread = threading.Thread(target=retry)
        thread.start()
        assert waiting.wait(60), "the retry never reached the upload's lock"
        assert not second  # it waits while the first request still streams
        first.sendall(data[MiB:])
        assert _response(first)[0] == 204
    thread.join(60)
    (status, body), = second
    assert status == 409, body
    # Refused for what the first request did (it completed the upload), not by a lock timeout.
    assert b"is complete (2097152 bytes)" in body and b"another request" not in body
    assert services.staging.file(capture["id"], "images/000000/a.png").read_bytes() == data


def test_events_arrive_while_the_job_runs(server, tmp_path):
    base, services = server
    store = services.store
    job = store.create("local", "reconstruct", {}, capture_id=None)
    seen: list[dict] = []
    release = threading.Event()
    in_time = []

    def worker():
        from worker.store import Owner

        owner = Owner.current()
        store.claim(job.id, owner, 30, 3)
        store.heartbeat(job.id, owner, 30, {"fraction": 0.5, "stage": "train"})
        in_time.append(release.wait(10))
        store.finish(job.id, owner, "succeeded")

    thread = threading.Thread(target=worker, daemon=True)
    deadline = time.monotonic() + 60
    with httpx.stream("GET", f"{base}/v1/jobs/{job.id}/events", timeout=30) as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        buffer = ""
        for text in r.iter_text():
            assert time.monotonic() < deadline, f"the stream did not end: {seen}"
            buffer += text
            while "\n\n" in buffer:
                block, buffer = buffer.split("\n\n", 1)
                seen += parse_sse(block + "\n\n")
                if thread.ident is None:
                    thread.start()  # the job starts once the stream has its first state
                if any(e.get("event") == "progress" for e in seen):
                    release.set()  # the progress came while the job was still running
    thread.join()
    assert in_time == [True]  # the progress event reached the client while the job ran
    states = [e["data"]["state"] for e in seen if e.get("event") == "state"]
    assert states == ["queued", "running", "succeeded"]
    progress = [e for e in seen if e.get("event") == "progress"]
    assert progress and progress[0]["data"]["fraction"] == 0.5
    last = progress[0]["id"]
    again = httpx.get(f"{base}/v1/jobs/{job.id}/events", headers={"Last-Event-ID": str(last)})
    assert [e["data"]["state"] for e in parse_sse(again.text)] == ["succeeded"]
