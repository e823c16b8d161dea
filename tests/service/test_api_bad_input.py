"""Every decoder the API runs on a client's bytes, fed malformed input: environment maps (EXR,
HDR) at POST /v1/assets; capture images (PNG, JPEG, EXR) and capture.json inside a zip at
POST /v1/captures/archive (the same commit as tus uploads); the zip itself; JSON request
bodies. Each is truncated, has the wrong magic bytes, is huge (headers written by hand) and
is empty; each answers 422 (413 for a body over a byte limit) naming the file the way the
client knows it, never a server folder, and keeps nothing."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from service_harness import ZIP, capture_files, make_settings, make_zip

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bad_inputs import EXTS, HUGE, bad_variants, good_image, png_header  # noqa: E402

from service.app import create_app

CASES = ("truncated header", "truncated pixels", "wrong magic", "empty", "no pixels", "huge")



def assert_clean(r, settings, status: int = 422) -> dict:
    assert r.status_code == status, r.text
    assert str(settings.data_dir) not in r.text and str(settings.scratch) not in r.text
    return r.json()["error"]


@pytest.mark.parametrize("fmt", ["exr", "hdr"])
@pytest.mark.parametrize("case", CASES)
def test_bad_envmaps_answer_422_naming_the_asset(client, settings, services, tmp_path, fmt,
                                                 case):
    data, words = bad_variants(fmt, good_image(fmt, tmp_path, 64, 32))[case]
    name = f"sky{EXTS[fmt]}"
    error = assert_clean(client.post("/v1/assets", params={"filename": name}, content=data),
                         settings)
    assert error["code"] == "invalid_asset" and error["message"].startswith(f"{name}: ")
    assert words in error["message"] and error["details"][0]["path"] == name
    assert services.blobs.list("assets") == []


def _capture_with(synth_capture: Path, path: str, data: bytes) -> dict[str, bytes]:
    files = capture_files(synth_capture)
    del files["images/000000/cam01.png"]
    return {**files, path: data}


@pytest.mark.parametrize("fmt", ["png", "jpeg", "exr"])
@pytest.mark.parametrize("case", CASES)
def test_bad_capture_images_answer_422_naming_the_file(client, settings, synth_capture,
                                                       tmp_path, fmt, case):
    data, words = bad_variants(fmt, good_image(fmt, tmp_path, 32, 32))[case]
    path = f"images/000000/cam01{EXTS[fmt]}"
    body = make_zip(_capture_with(synth_capture, path, data))
    error = assert_clean(client.post("/v1/captures/archive", content=body, headers=ZIP),
                         settings)
    assert error["code"] == "invalid_capture", error
    hits = [d for d in error["details"] if d["path"] == path]
    assert hits and words in hits[0]["message"], error["details"]
    assert client.get("/v1/captures").json()["items"] == []


def test_a_20000_pixel_square_png_is_refused_from_its_header(client, settings, synth_capture):
    body = make_zip(_capture_with(synth_capture, "images/000000/cam01.png", png_header(*HUGE)))
    error = assert_clean(client.post("/v1/captures/archive", content=body, headers=ZIP),
                         settings)
    assert "images/000000/cam01.png: is 20000x20000 (400000000 pixels); the limit is " \
           "150000000 pixels" in error["message"]


def test_the_pixel_limit_is_a_setting(tmp_path, synth_capture):
    settings = make_settings(tmp_path / "d", max_image_pixels=32 * 32 - 1)
    with TestClient(create_app(settings)) as client:
        body = make_zip(capture_files(synth_capture))
        error = assert_clean(client.post("/v1/captures/archive", content=body, headers=ZIP),
                             settings)
        assert "the limit is 1023 pixels" in error["message"]
        assert client.get("/v1/info").json()["limits"]["max_image_pixels"] == 1023


@pytest.mark.parametrize("data, words", [
    (b'{"frames": ["000000"], "cameras": [', "capture.json: cannot parse JSON"),
    (b"\x89PNG\r\n\x1a\n", "capture.json: cannot parse JSON"),
    (b"[" * 100_000, "nested too deeply"),
    (b"", "capture.json: cannot parse JSON"),
])
def test_a_bad_capture_json_answers_422(client, settings, synth_capture, data, words):
    files = {**capture_files(synth_capture), "capture.json": data}
    r = client.post("/v1/captures/archive?format=canonical", content=make_zip(files),
                    headers=ZIP)
    error = assert_clean(r, settings)
    assert words in error["message"] and error["details"][0]["path"] == "capture.json"


def test_a_json_file_over_the_json_limit_is_refused_in_the_manifest(tmp_path):
    settings = make_settings(tmp_path / "d", max_json_file_bytes=1024)
    with TestClient(create_app(settings)) as client:
        r = client.post("/v1/captures", json={"format": "canonical", "manifest": {"files": [
            {"path": "capture.json", "size": 1025, "sha256": "0" * 64}]}})
        error = assert_clean(r, settings)
        assert "a JSON file (parsed whole, in memory) may have 1024" in error["message"]


@pytest.mark.parametrize("body, status, words", [
    (lambda z: z[:len(z) // 2], 422, "not a zip archive"),
    (lambda z: b"Rar!\x1a\x07\x00" + bytes(200), 422, "not a zip archive"),
    (lambda z: b"Rar!" + z[4:], 422, "corrupt archive: Bad magic number for file header"),
    (lambda z: b"", 422, "not a zip archive"),
    (lambda z: make_zip({"capture.json": b"{}", "images/000000/cam00.png": bytes(4 << 20)}),
     422, "zip bomb"),
])
def test_bad_zips_answer_4xx(client, settings, synth_capture, body, status, words):
    zipped = make_zip(capture_files(synth_capture))
    r = client.post("/v1/captures/archive", content=body(zipped), headers=ZIP)
    assert words in assert_clean(r, settings, status)["message"]


@pytest.mark.parametrize("body, words", [
    (b'{"format": "canonical", "manifest": {"files": [', "body: not valid JSON at character"),
    (b"\x89PNG\r\n\x1a\n", "body: not UTF-8 text (byte 0 is 0x89)"),
    (b'{"format": ' + b"[" * 100_000, "body: the JSON is nested too deeply"),
    (b"[" * 100_000, "body: expected a JSON object"),  # refused before it is parsed
    (b'{"format": "auto", "manifest": {"files": [{"path": "a", "size": 1' + b"0" * 5000,
     "body: a JSON number has more than"),
    (b"", "body: Field required"),
])
def test_bad_json_bodies_answer_422(client, settings, body, words):
    r = client.post("/v1/captures", content=body, headers={"Content-Type": "application/json"})
    assert words in assert_clean(r, settings)["message"]


def test_the_leak_scan_sees_error_bodies_and_job_errors(leak_scan, settings):
    """The session-wide scan (conftest.no_server_paths) is wired and catches a leak."""
    seen = leak_scan.errors_seen
    with TestClient(create_app(settings)) as client:
        assert client.get("/v1/captures/cap_nope").status_code == 404
    assert leak_scan.errors_seen == seen + 1
    before = len(leak_scan.leaks)
    folder = f"{leak_scan.folder}/x/data/uploads/cap_1/files/images/a.png"
    leak_scan.check("GET", "/v1/jobs/j", 200, json.dumps(
        {"state": "failed", "error": {"message": f"cannot read '{folder}'"}}), sent="")
    leak_scan.check("GET", "/v1/jobs/j", 422, f"bad: {folder}", sent=f"param={folder}")
    assert [x.status for x in leak_scan.leaks[before:]] == [200]
    del leak_scan.leaks[before:]
