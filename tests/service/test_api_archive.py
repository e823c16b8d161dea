"""POST /v1/captures/archive: a small capture as one zip. A good one is ready in one request;
every bad one (traversal, symlinks, bombs, too big, not a zip, not a capture) is refused with
a clear 4xx and leaves no row, no staged file and no stored blob."""

from __future__ import annotations

import io
import stat
import zipfile

import pytest
from fastapi.testclient import TestClient
from service_harness import ZIP, capture_files, make_settings, make_zip
from sqlalchemy import func, select

from service.app import create_app
from worker.models import Capture




def assert_nothing_left(services) -> None:
    with services.store.session(write=False) as s:
        assert s.scalar(select(func.count()).select_from(Capture)) == 0
    staged = [p for p in services.staging.root.rglob("*") if p.is_file()]
    assert staged == []
    assert services.blobs.list("captures") == []


def test_a_zipped_capture_is_ready_in_one_request(client, services, synth_capture):
    files = capture_files(synth_capture)
    r = client.post("/v1/captures/archive?name=zipped", content=make_zip(files, "mycapture/"),
                    headers=ZIP)
    assert r.status_code == 201, r.text
    out = r.json()
    assert out["state"] == "ready" and out["name"] == "zipped" and out["format"] == "auto"
    assert out["summary"]["cameras"] == 8 and out["summary"]["source_format"] == "canonical"
    assert r.headers["Location"].endswith(f"/v1/captures/{out['id']}")
    root = services.blobs.local_path(f"captures/{out['id']}")
    assert (root / "capture.json").read_bytes() == files["capture.json"]
    listing = client.get(f"/v1/captures/{out['id']}/files").json()["items"]
    assert {f["path"] for f in listing} == set(files)
    assert [p for p in services.staging.root.rglob("*") if p.is_file()] == []


def _symlink_zip() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("capture.json", b"{}")
        link = zipfile.ZipInfo("images/000000/cam00.png")
        link.external_attr = (stat.S_IFLNK | 0o777) << 16
        zf.writestr(link, b"/etc/passwd")
    return buf.getvalue()


@pytest.mark.parametrize("body, words", [
    (make_zip({"capture.json": b"{}", "../evil.png": b"x"}), "'.' or '..'"),
    (make_zip({"capture.json": b"{}", "/etc/cron.d/evil": b"x"}), "absolute"),
    (make_zip({"capture.json": b"{}", "images\\000000\\cam.png": b"x"}), "backslash"),
    (_symlink_zip(), "symlink"),
    (make_zip({"capture.json": b"{}", "images/000000/cam00.png": bytes(8 << 20)}), "zip bomb"),
    (b"PK\x03\x04 this is not really a zip", "not a zip archive"),
    (make_zip({"capture.json": b"{}", "images/000000/cam00.png": bytes(4096)})[:-40],
     "not a zip archive"),  # truncated: the central directory is cut off
    (make_zip({"notes.txt": b"hello"}), "no known format"),
])
def test_bad_archives_leave_nothing(client, services, body, words):
    r = client.post("/v1/captures/archive", content=body, headers=ZIP)
    assert r.status_code in (400, 422), r.text
    assert words in r.json()["error"]["message"]
    assert_nothing_left(services)


def test_canonical_archives_hold_only_capture_content(client, services, synth_capture):
    files = {**capture_files(synth_capture), "gt/extra.txt": b"ground truth"}
    r = client.post("/v1/captures/archive?format=canonical", content=make_zip(files),
                    headers=ZIP)
    assert r.status_code == 422 and "gt/extra.txt" in r.json()["error"]["message"]
    assert_nothing_left(services)


def test_an_invalid_capture_in_a_zip_leaves_nothing(client, services, synth_capture):
    files = capture_files(synth_capture)
    files["images/000000/cam02.png"] = b"truncated"
    r = client.post("/v1/captures/archive", content=make_zip(files), headers=ZIP)
    assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_capture"
    assert r.json()["error"]["details"][0]["path"] == "images/000000/cam02.png"
    assert_nothing_left(services)


def test_archive_limits(tmp_path, synth_capture):
    settings = make_settings(tmp_path / "d", max_archive_bytes=10_000, max_archive_members=5)
    client = TestClient(create_app(settings))
    services = client.app.state.services
    body = make_zip(capture_files(synth_capture), method=zipfile.ZIP_STORED)
    assert len(body) > 10_000
    r = client.post("/v1/captures/archive", content=body, headers=ZIP)
    assert r.status_code == 413 and "10000" in r.json()["error"]["message"]

    def chunks():  # no Content-Length: refused while it streams in
        for i in range(0, len(body), 4096):
            yield body[i:i + 4096]

    r = client.post("/v1/captures/archive", content=chunks(), headers=ZIP)
    assert r.status_code == 413
    small = make_zip({f"f{i}": b"x" for i in range(6)})
    r = client.post("/v1/captures/archive", content=small, headers=ZIP)
    assert r.status_code == 413 and "members" in r.json()["error"]["message"]
    assert_nothing_left(services)
    assert list((services.staging.root / ".tmp").iterdir()) == []
