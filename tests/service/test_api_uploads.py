"""tus 1.0.0 on /v1/uploads: the protocol (headers, offsets, checksums, termination) and every
way an upload can go wrong, each leaving nothing half-written."""

from __future__ import annotations

import base64
import hashlib

import pytest
from service_harness import TUS, metadata, tus_create, tus_patch, upload_file

DATA = bytes(range(256)) * 40  # 10 240 bytes
FILES = {"capture.json": b"{}", "images/000000/cam00.png": DATA}


@pytest.fixture
def capture(new_capture) -> dict:
    return new_capture(FILES)


def _state(client, capture_id: str) -> dict:
    return client.get(f"/v1/captures/{capture_id}").json()["files"]


def _parts(services, capture_id: str) -> list[str]:
    parts = services.staging.parts_dir(capture_id)
    return sorted(p.name for p in parts.glob("*.part")) if parts.exists() else []


def test_options_advertises_the_protocol(client):
    r = client.options("/v1/uploads")
    assert r.status_code == 204
    assert r.headers["Tus-Version"] == "1.0.0" and r.headers["Tus-Resumable"] == "1.0.0"
    assert set(r.headers["Tus-Extension"].split(",")) == {"creation", "termination", "checksum"}
    assert set(r.headers["Tus-Checksum-Algorithm"].split(",")) == {"sha1", "sha256", "md5"}
    assert int(r.headers["Tus-Max-Size"]) == client.app.state.services.settings.max_file_bytes


def test_every_request_needs_tus_resumable(client, capture):
    r = client.post("/v1/uploads", headers={"Upload-Length": "2", "Upload-Metadata": metadata(
        capture=capture["id"], path="capture.json")})
    assert r.status_code == 412 and r.headers["Tus-Version"] == "1.0.0"
    assert r.headers["Tus-Resumable"] == "1.0.0"
    assert r.json()["error"]["code"] == "precondition_failed"


def test_create_head_patch_in_chunks(client, services, capture):
    r = tus_create(client, capture["id"], "images/000000/cam00.png", len(DATA))
    assert r.status_code == 201 and r.headers["Tus-Resumable"] == "1.0.0"
    url = r.headers["Location"]
    assert url.startswith("/v1/uploads/upl_")  # relative: no DGS_PUBLIC_URL, never the Host
    head = client.head(url, headers=TUS)
    assert head.status_code == 200 and head.headers["Upload-Offset"] == "0"
    assert head.headers["Upload-Length"] == str(len(DATA))
    assert head.headers["Cache-Control"] == "no-store"
    r = tus_patch(client, url, 0, DATA[:4000])
    assert r.status_code == 204 and r.headers["Upload-Offset"] == "4000"
    assert client.head(url, headers=TUS).headers["Upload-Offset"] == "4000"
    assert _state(client, capture["id"])["received"] == 0
    r = tus_patch(client, url, 4000, DATA[4000:])
    assert r.status_code == 204 and r.headers["Upload-Offset"] == str(len(DATA))
    staged = services.staging.file(capture["id"], "images/000000/cam00.png")
    assert staged.read_bytes() == DATA
    assert _parts(services, capture["id"]) == []
    files = _state(client, capture["id"])
    assert files["received"] == 1 and files["missing_paths"] == ["capture.json"]


def test_offset_mismatch_is_409_and_changes_nothing(client, capture):
    url = tus_create(client, capture["id"], "images/000000/cam00.png", len(DATA)).headers[
        "Location"]
    assert tus_patch(client, url, 0, DATA[:100]).status_code == 204
    r = tus_patch(client, url, 50, DATA[50:200])
    assert r.status_code == 409 and r.headers["Upload-Offset"] == "100"
    assert "HEAD" in r.json()["error"]["message"]
    assert client.head(url, headers=TUS).headers["Upload-Offset"] == "100"


def test_patch_needs_the_offset_content_type(client, capture):
    url = tus_create(client, capture["id"], "capture.json", 2).headers["Location"]
    r = client.patch(url, content=b"{}", headers={**TUS, "Upload-Offset": "0",
                                                   "Content-Type": "application/octet-stream"})
    assert r.status_code == 415
    assert client.head(url, headers=TUS).headers["Upload-Offset"] == "0"


def test_per_request_checksum(client, services, capture):
    url = tus_create(client, capture["id"], "images/000000/cam00.png", len(DATA)).headers[
        "Location"]
    chunk = DATA[:3000]
    good = base64.b64encode(hashlib.sha1(chunk).digest()).decode()
    bad = base64.b64encode(hashlib.sha1(b"other").digest()).decode()
    r = tus_patch(client, url, 0, chunk, {"Upload-Checksum": f"sha1 {bad}"})
    assert r.status_code == 460 and r.json()["error"]["code"] == "checksum_mismatch"
    assert client.head(url, headers=TUS).headers["Upload-Offset"] == "0"
    part = services.staging.parts_dir(capture["id"]) / f"{url.rsplit('/', 1)[1]}.part"
    assert part.stat().st_size == 0  # the refused bytes were cut off
    r = tus_patch(client, url, 0, chunk, {"Upload-Checksum": f"sha1 {good}"})
    assert r.status_code == 204 and r.headers["Upload-Offset"] == "3000"
    md5 = base64.b64encode(hashlib.md5(DATA[3000:]).digest()).decode()
    r = tus_patch(client, url, 3000, DATA[3000:], {"Upload-Checksum": f"md5 {md5}"})
    assert r.status_code == 204
    assert _state(client, capture["id"])["received"] == 1


@pytest.mark.parametrize("header", ["crc32 AAAA", "sha1 not-base64!", "sha256 AAAA"])
def test_bad_checksum_headers_are_400(client, capture, header):
    url = tus_create(client, capture["id"], "capture.json", 2).headers["Location"]
    r = tus_patch(client, url, 0, b"{}", {"Upload-Checksum": header})
    assert r.status_code == 400 and "Upload-Checksum" in r.json()["error"]["message"]


def test_wrong_sha256_is_460_and_shown_corrupt(client, services, capture):
    bad = bytearray(DATA)
    bad[-1] ^= 0xFF
    url = tus_create(client, capture["id"], "images/000000/cam00.png", len(DATA)).headers[
        "Location"]
    r = tus_patch(client, url, 0, bytes(bad))
    assert r.status_code == 460
    error = r.json()["error"]
    assert error["code"] == "checksum_mismatch" and "images/000000/cam00.png" in error["message"]
    assert _parts(services, capture["id"]) == []
    assert not services.staging.file(capture["id"], "images/000000/cam00.png").exists()
    files = _state(client, capture["id"])
    assert files["corrupt_paths"] == ["images/000000/cam00.png"] and files["received"] == 0
    assert client.head(url, headers=TUS).status_code == 404
    listing = client.get(f"/v1/captures/{capture['id']}/files?state=corrupt").json()
    assert [f["path"] for f in listing["items"]] == ["images/000000/cam00.png"]
    upload_file(client, capture["id"], "images/000000/cam00.png", DATA)  # a new POST retries
    files = _state(client, capture["id"])
    assert files["corrupt"] == 0 and files["received"] == 1


def test_a_truncated_upload_is_never_part_of_the_capture(client, services, capture):
    """A file whose upload stopped short stays missing: commit answers 409 naming it, nothing
    is frozen, and the upload resumes where it stopped."""
    upload_file(client, capture["id"], "capture.json", b"{}")
    url = tus_create(client, capture["id"], "images/000000/cam00.png", len(DATA)).headers[
        "Location"]
    assert tus_patch(client, url, 0, DATA[:4000]).status_code == 204
    r = client.post(f"/v1/captures/{capture['id']}/commit")
    assert r.status_code == 409, r.text
    error = r.json()["error"]
    assert error["code"] == "files_missing"
    assert [d["path"] for d in error["details"]] == ["images/000000/cam00.png"]
    assert not services.staging.file(capture["id"], "images/000000/cam00.png").exists()
    assert services.blobs.list(f"captures/{capture['id']}") == []
    files = _state(client, capture["id"])
    assert files["missing_paths"] == ["images/000000/cam00.png"] and files["corrupt"] == 0
    assert client.get(f"/v1/captures/{capture['id']}").json()["state"] == "uploading"
    assert client.head(url, headers=TUS).headers["Upload-Offset"] == "4000"
    assert tus_patch(client, url, 4000, DATA[4000:]).status_code == 204
    assert services.staging.file(capture["id"], "images/000000/cam00.png").read_bytes() == DATA


def test_body_past_upload_length_is_413(client, services, capture):
    url = tus_create(client, capture["id"], "capture.json", 2).headers["Location"]
    r = tus_patch(client, url, 0, b"{}  ")
    assert r.status_code == 413
    assert client.head(url, headers=TUS).headers["Upload-Offset"] == "0"

    def chunked():  # no Content-Length: refused while streaming
        yield b"{"
        yield b"}  "

    r = client.patch(url, content=chunked(), headers={
        **TUS, "Upload-Offset": "0", "Content-Type": "application/offset+octet-stream"})
    assert r.status_code == 413
    assert client.head(url, headers=TUS).headers["Upload-Offset"] == "0"
    part = services.staging.parts_dir(capture["id"]) / f"{url.rsplit('/', 1)[1]}.part"
    assert part.stat().st_size == 0


@pytest.mark.parametrize("path, status", [
    ("../escape.png", 400), ("/etc/passwd", 400), ("images/../../x", 400),
    ("images\\000000\\cam00.png", 400), ("images/000000/cam00.png\x00", 400),
    ("images/000000/other.png", 422)])
def test_creation_refuses_paths_outside_the_manifest(client, services, capture, path, status):
    r = tus_create(client, capture["id"], path, 2)
    assert r.status_code == status, r.text
    assert r.headers["Tus-Resumable"] == "1.0.0"
    assert _parts(services, capture["id"]) == []


def test_creation_checks_length_metadata_and_state(client, capture, new_capture):
    r = tus_create(client, capture["id"], "capture.json", 3)
    assert r.status_code == 422 and "manifest declares 2 bytes" in r.json()["error"]["message"]
    r = client.post("/v1/uploads", headers={**TUS, "Upload-Length": "2"})
    assert r.status_code == 400 and "Upload-Metadata" in r.json()["error"]["message"]
    r = client.post("/v1/uploads", headers={**TUS, "Upload-Length": "-1", "Upload-Metadata":
                                            metadata(capture=capture["id"], path="x")})
    assert r.status_code == 400
    r = client.post("/v1/uploads", headers={**TUS, "Upload-Length": "2",
                                            "Upload-Metadata": "capture %%%"})
    assert r.status_code == 400
    r = tus_create(client, "cap_missing", "capture.json", 2)
    assert r.status_code == 404
    big = client.app.state.services.settings.max_file_bytes + 1
    assert tus_create(client, capture["id"], "capture.json", big).status_code == 413
    # `filename` is accepted in place of `path` (Uppy's default metadata)
    r = client.post("/v1/uploads", headers={**TUS, "Upload-Length": "2", "Upload-Metadata":
                                            metadata(capture=capture["id"],
                                                     filename="capture.json")})
    assert r.status_code == 201


def test_resending_a_received_file_is_a_no_op(client, services, capture):
    upload_file(client, capture["id"], "images/000000/cam00.png", DATA)
    staged = services.staging.file(capture["id"], "images/000000/cam00.png")
    before = staged.stat()
    upload_file(client, capture["id"], "images/000000/cam00.png", DATA)
    assert staged.stat().st_ino == before.st_ino and staged.stat().st_mtime_ns == before.st_mtime_ns
    # a re-send with other bytes is refused and the received file stays
    bad = bytes(reversed(DATA))
    url = tus_create(client, capture["id"], "images/000000/cam00.png", len(DATA)).headers[
        "Location"]
    assert tus_patch(client, url, 0, bad).status_code == 460
    assert staged.read_bytes() == DATA
    assert _parts(services, capture["id"]) == []
    assert _state(client, capture["id"])["received"] == 1


def test_termination(client, services, capture):
    url = tus_create(client, capture["id"], "images/000000/cam00.png", len(DATA)).headers[
        "Location"]
    assert tus_patch(client, url, 0, DATA[:500]).status_code == 204
    r = client.delete(url, headers=TUS)
    assert r.status_code == 204 and r.headers["Tus-Resumable"] == "1.0.0"
    assert _parts(services, capture["id"]) == []
    assert client.head(url, headers=TUS).status_code == 404
    assert tus_patch(client, url, 500, DATA[500:]).status_code == 404
    done = tus_create(client, capture["id"], "capture.json", 2).headers["Location"]
    assert tus_patch(client, done, 0, b"{}").status_code == 204
    assert client.delete(done, headers=TUS).status_code == 409  # the file belongs to the capture
    assert _state(client, capture["id"])["received"] == 1


def test_empty_file_completes_at_creation(client, new_capture):
    capture = new_capture({"capture.json": b"{}", "images/000000/empty.png": b""})
    r = tus_create(client, capture["id"], "images/000000/empty.png", 0)
    assert r.status_code == 201
    assert client.head(r.headers["Location"], headers=TUS).headers["Upload-Offset"] == "0"
    assert _state(client, capture["id"])["received"] == 1


def test_a_restarted_process_rehashes_the_prefix(client, services, capture):
    url = tus_create(client, capture["id"], "images/000000/cam00.png", len(DATA)).headers[
        "Location"]
    assert tus_patch(client, url, 0, DATA[:6000]).status_code == 204
    services.hashes.drop(url.rsplit("/", 1)[1])  # what a restart forgets
    assert tus_patch(client, url, 6000, DATA[6000:]).status_code == 204
    assert _state(client, capture["id"])["received"] == 1


def test_bytes_past_the_committed_offset_are_cut_off(client, services, capture):
    """A crash between writing and recording the offset leaves extra bytes in the part file;
    the next PATCH starts at the recorded offset."""
    url = tus_create(client, capture["id"], "images/000000/cam00.png", len(DATA)).headers[
        "Location"]
    assert tus_patch(client, url, 0, DATA[:1000]).status_code == 204
    part = services.staging.parts_dir(capture["id"]) / f"{url.rsplit('/', 1)[1]}.part"
    with open(part, "ab") as f:
        f.write(b"garbage written before a crash")
    assert tus_patch(client, url, 1000, DATA[1000:]).status_code == 204
    assert services.staging.file(capture["id"], "images/000000/cam00.png").read_bytes() == DATA


def test_uploads_stop_once_committing_or_ready(client, ready_capture):
    capture_id = ready_capture()
    r = tus_create(client, capture_id, "capture.json", 10)
    assert r.status_code == 409 and "ready" in r.json()["error"]["message"]



def test_browsers_on_allowed_origins_can_speak_tus(tmp_path):
    from fastapi.testclient import TestClient
    from service_harness import make_settings

    from service.app import create_app

    origin = "https://studio.example.com"
    client = TestClient(create_app(make_settings(tmp_path / "d", cors_origins=[origin])))
    r = client.options("/v1/uploads", headers={
        "Origin": origin, "Access-Control-Request-Method": "PATCH",
        "Access-Control-Request-Headers": "tus-resumable,upload-offset,content-type"})
    assert r.status_code == 200 and r.headers["access-control-allow-origin"] == origin
    r = client.options("/v1/uploads", headers={"Origin": origin})  # tus discovery, not CORS
    assert r.status_code == 204 and r.headers["Tus-Version"] == "1.0.0"
    exposed = r.headers["access-control-expose-headers"].lower()
    assert "upload-offset" in exposed and "location" in exposed
    other = client.options("/v1/uploads", headers={
        "Origin": "https://evil.example.com", "Access-Control-Request-Method": "PATCH"})
    assert "access-control-allow-origin" not in other.headers


def test_a_long_body_is_made_durable_while_it_streams(client, app, services, new_capture):
    """Every upload_sync_bytes an fsync runs beside the receiving and records the offset it
    covers, while the request is still open: a crash then keeps what was synced."""
    import asyncio
    import os

    import httpx

    from service.lookups import get_upload

    mib = 1 << 20
    services.settings = services.settings.model_copy(update={"upload_sync_bytes": mib})
    data = os.urandom(10 * mib + 123)
    cap = new_capture({"capture.json": b"{}", "images/000000/cam00.png": data})
    url = tus_create(client, cap["id"], "images/000000/cam00.png", len(data)).headers["Location"]
    upload_id = url.rsplit("/", 1)[1]
    seen: list[int] = []

    async def body():
        step = 256 << 10
        for i in range(0, len(data), step):
            yield data[i:i + step]
            if i + step == 6 * mib:
                await asyncio.sleep(0.2)  # the first 4 MiB block is written meanwhile
            if i + step == 7 * mib:  # the chunks since then started its sync: wait for it
                for _ in range(500):
                    offset = get_upload(services.store, upload_id, "local").offset
                    if offset > 0:
                        break
                    await asyncio.sleep(0.01)
                seen.append(offset)

    async def patch():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://testserver") as c:
            return await c.patch(url, content=body(), headers={
                **TUS, "Upload-Offset": "0", "Content-Length": str(len(data)),
                "Content-Type": "application/offset+octet-stream"})

    r = asyncio.run(patch())
    assert r.status_code == 204 and r.headers["Upload-Offset"] == str(len(data))
    assert seen and seen[0] >= 4 * mib and seen[0] % (4 * mib) == 0  # recorded mid-request
    assert services.staging.file(cap["id"], "images/000000/cam00.png").read_bytes() == data
