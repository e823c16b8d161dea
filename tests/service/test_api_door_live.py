"""Issue 20's bad requests (malformed uploads, server folders in messages, tus edge cases)
replayed against a real `dgs serve` (API and embedded worker, fresh data folder): each gets a
4xx that says what is wrong, naming files as the client knows them; nothing answers 500 and no
answer or job error shows the server's data folder."""

from __future__ import annotations

import base64
import io
import sys
import time
import zipfile
from pathlib import Path

import httpx
import pytest
from service_harness import TUS, capture_files, manifest_of, metadata

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bad_inputs import HUGE, bad_variants, good_image, png_header  # noqa: E402
from live_server import LiveServer  # noqa: E402

pytestmark = pytest.mark.timeout(420)
ZIP = {"Content-Type": "application/zip"}


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    data = tmp_path_factory.mktemp("door-live") / "data"
    server = LiveServer(data, data.parent / "serve.log").start()
    with httpx.Client(base_url=server.url, timeout=60) as http:
        yield server, http
    server.stop()


def _zip(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for path, data in files.items():
            zf.writestr(path, data)
    return buf.getvalue()


def _refused(r: httpx.Response, server: LiveServer, status: int = 422) -> dict:
    assert r.status_code == status, r.text
    assert str(server.data_dir) not in r.text
    return r.json()["error"]


def test_malformed_uploads_answer_422_naming_the_client_file(live, synth_capture, tmp_path):
    server, http = live
    exr = good_image("exr", tmp_path, 64, 32)
    error = _refused(http.post("/v1/assets", params={"filename": "studio.exr"},
                               content=exr[:len(exr) // 2]), server)  # a truncated EXR
    assert error["code"] == "invalid_asset" and error["message"].startswith("studio.exr: ")
    hdr, words = bad_variants("hdr", good_image("hdr", tmp_path, 64, 32))["wrong magic"]
    assert words in _refused(http.post("/v1/assets", params={"filename": "sky.hdr"},
                                       content=hdr), server)["message"]
    files = capture_files(synth_capture)
    files["images/000000/cam01.png"] = png_header(*HUGE)  # 20000 x 20000 inside a zip
    error = _refused(http.post("/v1/captures/archive", content=_zip(files), headers=ZIP), server)
    assert error["details"][0]["path"] == "images/000000/cam01.png"
    assert "is 20000x20000 (400000000 pixels); the limit is" in error["message"]
    error = _refused(http.post("/v1/captures", content=b"\x89PNG\r\n\x1a\n",
                               headers={"Content-Type": "application/json"}), server)
    assert "not UTF-8" in error["message"]


def _tus_upload(http: httpx.Client, capture_id: str, path: str, data: bytes) -> str:
    r = http.post("/v1/uploads", headers={**TUS, "Upload-Length": str(len(data)),
                                          "Upload-Metadata": metadata(capture=capture_id,
                                                                      path=path)})
    assert r.status_code == 201, r.text
    url = r.headers["Location"]
    if data:
        r = http.patch(url, content=data, headers={
            **TUS, "Upload-Offset": "0", "Content-Type": "application/offset+octet-stream"})
        assert r.status_code == 204, r.text
    return url


def test_a_capture_by_tus_names_its_bad_file_and_tus_edges_are_refused(live, synth_capture):
    server, http = live
    files = capture_files(synth_capture)
    files["images/000000/cam03.png"] = b"not an image at all"
    capture = http.post("/v1/captures", json={"format": "canonical",
                                              "manifest": manifest_of(files)}).json()
    urls = {p: _tus_upload(http, capture["id"], p, d) for p, d in files.items()}
    error = _refused(http.post(f"/v1/captures/{capture['id']}/commit"), server)
    assert error["code"] == "invalid_capture"
    assert "images/000000/cam03.png: is not a PNG file (wrong magic bytes)" in error["message"]
    # Bytes after the last one of a complete upload: refused, not silently dropped.
    done = urls["capture.json"]
    r = http.patch(done, content=b"more", headers={
        **TUS, "Upload-Offset": str(len(files["capture.json"])),
        "Content-Type": "application/offset+octet-stream"})
    assert _refused(r, server, 413)["code"] == "payload_too_large"
    # A wrong checksum after 100 bytes names the bytes that were sent.
    big = {"images/000000/extra.png": bytes(300)}
    other = http.post("/v1/captures", json={"format": "auto",
                                            "manifest": manifest_of(big)}).json()
    r = http.post("/v1/uploads", headers={**TUS, "Upload-Length": "300", "Upload-Metadata":
                                          metadata(capture=other["id"],
                                                   path="images/000000/extra.png")})
    url = r.headers["Location"]
    patch = {**TUS, "Content-Type": "application/offset+octet-stream"}
    assert http.patch(url, content=bytes(100), headers={**patch, "Upload-Offset": "0"}) \
        .status_code == 204
    r = http.patch(url, content=bytes(50), headers={
        **patch, "Upload-Offset": "100",
        "Upload-Checksum": "sha1 " + base64.b64encode(bytes(20)).decode()})
    assert "the sha1 of the 50 bytes sent does not match" in _refused(r, server, 460)["message"]


def test_a_failed_job_names_the_capture_file_not_the_server_folder(live, synth_capture):
    server, http = live
    server.wait_worker()
    files = capture_files(synth_capture)
    r = http.post("/v1/captures/archive", content=_zip(files), headers=ZIP)
    assert r.status_code == 201, r.text
    capture_id = r.json()["id"]
    stored = server.data_dir / "store" / "captures" / capture_id / "images/000000/cam02.png"
    stored.write_bytes(stored.read_bytes()[:64])  # damaged in the store after its commit
    job = http.post("/v1/jobs", json={"capture_id": capture_id,
                                      "params": {"preset": "test"}}).json()
    deadline = time.monotonic() + 300
    while (state := http.get(f"/v1/jobs/{job['id']}").json())["state"] in ("queued", "running"):
        assert time.monotonic() < deadline, state
        time.sleep(0.5)
    assert state["state"] == "failed" and state["error"]["code"] == "invalid_input", state
    assert "images/000000/cam02.png" in state["error"]["message"]
    logs = http.get(f"/v1/jobs/{job['id']}/logs").text
    for text in (str(state), logs):
        assert str(server.data_dir) not in text
