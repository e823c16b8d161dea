"""service.client against a real uvicorn server on a loopback port: a capture folder uploaded
(canonical files only), resumed after a dropped connection and after a new process, committed;
a job followed over server-sent events across a dropped stream; artifacts downloaded with
Range resume and checked against their SHA-256."""

from __future__ import annotations

import base64
import hashlib
import shutil
import socket
import threading
import time
from pathlib import Path

import httpx
import pytest
import uvicorn
from service_harness import make_settings
from sqlalchemy import select
from test_api_artifacts import add_artifacts
from test_api_live import padded_png

from service.client import uploads as client_module
from service.app import create_app
from service.client import ApiError, Client, manifest_of
from worker.models import Job
from worker.store import Owner

MiB = 1 << 20
BIG = "images/000000/cam00.png"
pytestmark = pytest.mark.timeout(180)


@pytest.fixture
def server(tmp_path: Path):
    yield from _serve(make_settings(tmp_path / "data", sse_keepalive_seconds=0.2))


@pytest.fixture
def limited(tmp_path: Path):
    """A server that allows one job change at once, then one a minute; its limits' clock
    is `clock[0]` (seconds), which the client's `sleep` moves on."""
    yield from _serve(make_settings(tmp_path / "data", job_changes_burst=1,
                                    job_changes_per_minute=1))


def _serve(settings):
    app = create_app(settings)
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    srv = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    thread = threading.Thread(target=srv.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not srv.started:
        assert time.monotonic() < deadline and thread.is_alive(), "server did not start"
        time.sleep(0.02)
    yield f"http://127.0.0.1:{sock.getsockname()[1]}", app.state.services
    srv.should_exit = True
    thread.join(timeout=10)
    sock.close()


class Flaky(httpx.HTTPTransport):
    """A real transport that records requests and drops chosen ones: `drop(request)` says
    "before" (never sent), "after" (sent, the answer lost) or None."""

    def __init__(self, drop=lambda request: None):
        super().__init__()
        self.drop, self.requests = drop, []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        what = self.drop(request)
        if what == "before":
            raise httpx.WriteError("connection dropped", request=request)
        self.requests.append(request)
        response = super().handle_request(request)
        if what == "after":
            response.read()
            response.close()
            raise httpx.ReadError("connection dropped", request=request)
        return response

    def patched(self) -> list[int]:
        """Upload-Offset of every PATCH that reached the server."""
        return [int(r.headers["Upload-Offset"]) for r in self.requests if r.method == "PATCH"]


def _meta(request: httpx.Request) -> dict[str, str]:
    pairs = (item.split(" ") for item in request.headers["Upload-Metadata"].split(","))
    return {k: base64.b64decode(v).decode() for k, v in pairs}


@pytest.fixture
def folder(synth_capture: Path, tmp_path: Path) -> Path:
    """The synthetic capture with a 5 MiB first image (still a valid PNG)."""
    out = tmp_path / "capture"
    shutil.copytree(synth_capture, out)
    (out / BIG).write_bytes(padded_png((out / BIG).read_bytes(), 5 * MiB))
    return out


def test_manifest_holds_the_canonical_files_only(folder):
    paths = [f["path"] for f in manifest_of(folder)]
    assert "capture.json" in paths and BIG in paths
    assert not [p for p in paths if p.startswith("gt/")]  # ground truth stays here
    assert any(f["path"].startswith("gt/") for f in manifest_of(folder, "auto"))
    entry = next(f for f in manifest_of(folder) if f["path"] == BIG)
    assert entry["sha256"] == hashlib.sha256((folder / BIG).read_bytes()).hexdigest()
    with pytest.raises(ValueError, match="not a directory"):
        manifest_of(folder / "nowhere")


def test_upload_resumes_after_a_lost_answer(server, folder, monkeypatch):
    base, services = server
    monkeypatch.setattr(client_module, "CHUNK", MiB)
    lost = []

    def drop(request):  # the answer to the PATCH at 2 MiB of the big file never arrives
        if request.method == "PATCH" and request.headers["Upload-Offset"] == str(2 * MiB) \
                and not lost:
            lost.append(request.url)
            return "after"
        return None

    transport = Flaky(drop)
    seen = []
    with Client(base, transport=transport, chunk_checksum="sha1") as c:
        cap = c.create_capture(folder)
        assert cap["state"] == "uploading"
        sent = c.upload_capture(cap["id"], folder, progress=lambda d, t: seen.append((d, t)))
        total = sum(f["size"] for f in manifest_of(folder))
        assert sent == total and seen[-1] == (total, total)
        assert [d for d, _ in seen] == sorted(d for d, _ in seen)
        # The lost PATCH was not sent again: the client asked where the upload stood.
        big = [int(r.headers["Upload-Offset"]) for r in transport.requests
               if r.method == "PATCH" and r.url == lost[0]]
        assert big == [i * MiB for i in range(6)]
        assert (c.capture(cap["id"])["files"]["missing"]) == 0
        staged = services.staging.file(cap["id"], BIG)
        assert staged.read_bytes() == (folder / BIG).read_bytes()
        ready = c.commit(cap["id"])
        assert ready["state"] == "ready" and ready["summary"]["cameras"] == 8
        # Uploading a ready capture again sends nothing.
        assert c.upload_capture(cap["id"], folder) == 0


def test_another_process_resumes_from_the_url_store(server, folder, tmp_path, monkeypatch):
    base, services = server
    monkeypatch.setattr(client_module, "CHUNK", MiB)
    store = tmp_path / "uploads.json"

    def crash(request):  # the first process dies before its fourth PATCH of the big file
        if request.method == "PATCH" and request.headers["Upload-Offset"] == str(3 * MiB):
            return "before"
        return None

    first = Client(base, transport=Flaky(crash), url_store=store, chunk_checksum="sha1")
    cap = first.create_capture(folder)
    with pytest.raises(httpx.WriteError):
        first.upload_capture(cap["id"], folder, retries=0)
    first.close()
    assert BIG in [f["path"] for f in Client(base).missing_files(cap["id"])]
    transport = Flaky()
    with Client(base, transport=transport, url_store=store, chunk_checksum="sha1") as second:
        second.upload_capture(cap["id"], folder)
        assert second.commit(cap["id"])["state"] == "ready"
    # Resumed at 3 MiB: the first three MiB went over the wire once.
    assert transport.patched()[:3] == [3 * MiB, 4 * MiB, 5 * MiB]
    created = [_meta(r)["path"] for r in transport.requests
               if r.method == "POST" and r.url.path == "/v1/uploads"]
    assert BIG not in created and created  # the files after it were begun afresh
    assert services.blobs.local_path(f"captures/{cap['id']}/{BIG}").read_bytes() == \
        (folder / BIG).read_bytes()
    assert store.read_text() == "{}"  # finished uploads are forgotten


class CutBody(httpx.SyncByteStream):
    """A request body whose connection drops after `keep` bytes."""

    def __init__(self, inner, keep: int):
        self.inner, self.keep = inner, keep

    def __iter__(self):
        sent = 0
        for block in self.inner:
            if sent + len(block) > self.keep:
                raise httpx.WriteError("connection dropped")
            sent += len(block)
            yield block


def test_streamed_upload_resumes_after_a_dropped_connection(server, folder):
    """The default client streams each file in one PATCH; the connection drops 3 MiB into the
    big file, and the retry goes on from what the server kept."""
    base, services = server

    def drop(request):
        if request.method == "PATCH" and request.headers["Upload-Offset"] == "0" \
                and int(request.headers["Content-Length"]) > 4 * MiB:
            request.stream = CutBody(request.stream, 3 * MiB)
        return None

    transport = Flaky(drop)
    with Client(base, transport=transport) as c:
        cap = c.create_capture(folder)
        c.upload_capture(cap["id"], folder)
        assert c.commit(cap["id"])["state"] == "ready"
    patches = [r for r in transport.requests if r.method == "PATCH"]
    assert not [r for r in patches if "Upload-Checksum" in r.headers]
    big = [int(r.headers["Upload-Offset"]) for r in patches
           if int(r.headers["Content-Length"]) > MiB or r.headers["Upload-Offset"] != "0"]
    assert len(big) >= 2 and big[0] == 0 and 0 < big[-1] <= 3 * MiB  # resumed, not restarted
    assert services.blobs.local_path(f"captures/{cap['id']}/{BIG}").read_bytes() == \
        (folder / BIG).read_bytes()


def test_commit_errors_name_the_files(server, folder):
    base, _ = server
    with Client(base) as c:
        cap = c.create_capture(folder)
        with pytest.raises(ApiError) as missing:
            c.commit(cap["id"])
        assert missing.value.status == 409 and missing.value.code == "files_missing"
        assert BIG in {d["path"] for d in missing.value.details}
        (folder / "images/000000/cam03.png").write_bytes(b"not a png")
        broken = c.create_capture(folder)
        c.upload_capture(broken["id"], folder)
        with pytest.raises(ApiError) as invalid:
            c.commit(broken["id"])
        assert invalid.value.status == 422 and invalid.value.code == "invalid_capture"
        assert "cam03" in str(invalid.value)
        with pytest.raises(ApiError) as unknown:
            c.job("job_nope")
        assert unknown.value.status == 404 and not unknown.value.retryable


def _cut_streams(transport: Flaky, cut: threading.Event) -> None:
    """The first event stream breaks right after the chunk with its first progress event."""
    handle = transport.handle_request

    def handle_request(request):
        response = handle(request)
        if not request.url.path.endswith("/events") or cut.is_set():
            return response

        class Cut(httpx.SyncByteStream):
            def __iter__(self):
                for chunk in response.stream:
                    yield chunk
                    if b"event: progress" in chunk:
                        cut.set()
                        raise httpx.ReadError("connection dropped", request=request)

            def close(self):
                response.stream.close()

        return httpx.Response(response.status_code, headers=response.headers, stream=Cut(),
                              request=request)

    transport.handle_request = handle_request


def test_wait_follows_events_across_a_dropped_stream(server):
    base, services = server
    store = services.store
    job = store.create("local", "reconstruct", {}, capture_id=None)
    transport, cut, first = Flaky(), threading.Event(), threading.Event()
    _cut_streams(transport, cut)

    def worker():
        owner = Owner.current()
        assert first.wait(30)  # the stream has the job's state: what follows is news
        store.claim(job.id, owner, 30, 3)
        store.heartbeat(job.id, owner, 30, {"fraction": 0.5, "stage": "appearance"})
        assert cut.wait(30)
        store.heartbeat(job.id, owner, 30, {"fraction": 0.8, "stage": "geometry"})
        store.finish(job.id, owner, "succeeded")

    thread = threading.Thread(target=worker, daemon=True)
    thread.start()
    events = []

    def seen(event):
        events.append(event)
        first.set()

    with Client(base, transport=transport) as c:
        done = c.wait(job.id, on_event=seen, timeout=60)
    thread.join(10)
    assert done["state"] == "succeeded"
    streams = [r for r in transport.requests if r.url.path.endswith("/events")]
    assert len(streams) == 2 and "last-event-id" not in streams[0].headers
    ids = [e.id for e in events]
    assert ids == sorted(set(ids))  # nothing seen twice
    assert streams[1].headers["last-event-id"] == str(ids[[e.kind for e in events].index(
        "progress")])
    assert [e.data["fraction"] for e in events if e.kind == "progress"] == [0.5, 0.8]
    assert [e.data["state"] for e in events if e.kind == "state"] == [
        "queued", "running", "succeeded"]


def test_downloads_resume_with_range_and_are_checked(server, tmp_path):
    base, services = server
    blob = bytes(i % 251 for i in range(5000))
    run = {"frames/000000/gaussians.ply": blob, "metrics.json": b'{"psnr": 30}',
           "renders/000000/cam00_rgb.png": b"png" * 10}
    job = services.store.create("local", "reconstruct", {}, capture_id=None)
    add_artifacts(services, job.id, run, tmp_path)
    ply = "frames/000000/gaussians.ply"
    digest = hashlib.sha256(blob).hexdigest()
    out = tmp_path / "results"
    transport = Flaky()
    with Client(base, transport=transport) as c:
        part = out / (ply + ".part")
        part.parent.mkdir(parents=True)
        part.write_bytes(blob[:3000])  # an interrupted download
        assert c.download(job.id, ply, out / ply, sha256=digest).read_bytes() == blob
        assert transport.requests[-1].headers["range"] == "bytes=3000-"
        assert not part.exists()
        other = tmp_path / "other.ply"
        other.with_name("other.ply.part").write_bytes(b"x" * 3000)  # not the artifact's bytes
        with pytest.raises(ApiError, match="SHA-256"):
            c.download(job.id, ply, other, sha256=digest)
        assert not other.exists() and not other.with_name("other.ply.part").exists()
        assert c.download(job.id, ply, other, sha256=digest).read_bytes() == blob
        before = len(transport.requests)
        paths = c.download_all(job.id, out)
        assert [p.relative_to(out).as_posix() for p in paths] == sorted(run)
        for rel, data in run.items():
            assert (out / rel).read_bytes() == data
        # Only the listing was fetched for the PLY already there; the others were downloaded.
        fetched = [r.url.path for r in transport.requests[before:]]
        assert not [p for p in fetched if p.endswith("gaussians.ply")]
        assert [a["path"] for a in c.artifacts(job.id, "ply")] == [ply]
        with pytest.raises(ApiError) as gone:
            c.download(job.id, "frames/../../etc/passwd", tmp_path / "x")
        assert gone.value.status == 404


def test_a_submit_whose_answer_was_lost_is_sent_again_and_makes_one_job(server, folder):
    """Every submit carries an Idempotency-Key and is sent again with it after a lost answer, a
    timeout or a 5xx (issue 32): the job, the render and the export each exist once."""
    base, services = server
    lost: set[str] = set()

    def drop(request):  # the first answer to each submit never arrives; the server made it
        path = request.url.path
        if request.method == "POST" and path in ("/v1/jobs", "/v1/renders", "/v1/exports") \
                and path not in lost:
            lost.add(path)
            return "after"
        return None

    transport = Flaky(drop)
    with Client(base, transport=transport, retry_delay=0) as c:
        cap = c.create_capture(folder)
        c.upload_capture(cap["id"], folder)
        c.commit(cap["id"])
        job = c.submit(cap["id"], {"preset": "test"}, name="once")
        source = services.store.create("local", "reconstruct", {}, capture_id=cap["id"])
        owner = Owner.current()
        services.store.claim(source.id, owner, 5, 3)
        services.store.finish(source.id, owner, "succeeded")
        render = c.render(source.id, "builtin:studio", orbit=4)
        export = c.export(source.id, ("spz",))
    posts = [r for r in transport.requests if r.method == "POST" and r.url.path in lost]
    assert len(posts) == 6 and lost == {"/v1/jobs", "/v1/renders", "/v1/exports"}
    for path in lost:  # sent twice, with one key
        keys = [r.headers["Idempotency-Key"] for r in posts if r.url.path == path]
        assert len(keys) == 2 and keys[0] == keys[1]
    with services.store.session(write=False) as s:
        made = set(s.scalars(select(Job.id).where(Job.id != source.id)))
    assert made == {job["id"], render["id"], export["id"]} and job["name"] == "once"


def test_a_429_is_waited_out_for_its_retry_after_then_sent_again(limited, folder):
    """Issue 42: the client sleeps a 429's Retry-After (at most max_wait) and sends the
    request again; a submit keeps its Idempotency-Key. Its sleep drives the server's clock,
    so nothing really waits."""
    base, services = limited
    now, slept = [1_000_000.0], []
    services.limits.clock = lambda: now[0]

    def sleep(seconds: float) -> None:
        slept.append(seconds)
        now[0] += seconds

    transport = Flaky()
    with Client(base, transport=transport, sleep=sleep, max_wait=45) as c:
        cap = c.create_capture(folder)
        c.upload_capture(cap["id"], folder)
        c.commit(cap["id"])
        job = c.submit(cap["id"], {"preset": "test"})  # the one change allowed at once
        assert slept == []
        cancelled = c.cancel(job["id"])  # a token in 60 s: max_wait, then the 15 s left
        again = c.submit(cap["id"], {"preset": "test"})  # the same again
    assert cancelled["state"] == "cancelled" and again["id"] != job["id"]
    assert slept == [45, 15, 45, 15]
    posts = [r for r in transport.requests if r.method == "POST" and r.url.path == "/v1/jobs"]
    keys = [r.headers["Idempotency-Key"] for r in posts]
    assert len(keys) == 4 and keys[0] != keys[1] == keys[2] == keys[3]
    with pytest.raises(ApiError) as refused:  # the attempts spent: the 429 is raised
        with Client(base, sleep=lambda s: None, submit_attempts=2) as c:
            c.cancel(again["id"])
    assert refused.value.status == 429 and refused.value.code == "rate_limited"
    assert refused.value.retry_after == 60


@pytest.mark.parametrize("value, seconds", [("7", 7.0), ("0", 0.0), ("", None), ("soon", None),
                                            ("Wed, 21 Oct 2026 07:28:00 GMT", None),
                                            ("9" * 12, None)])
def test_retry_after_is_read_in_seconds(value, seconds):
    from service.client.http import retry_after

    r = httpx.Response(429, headers={"Retry-After": value} if value else {})
    assert retry_after(r) == seconds
