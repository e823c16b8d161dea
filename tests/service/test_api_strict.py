"""The door, second pass (issue 32), in process: every request model is as strict as the run
configuration (no strings or booleans for numbers), frame slices are bounded and checked against
the capture, names are printable and bounded, JSON bodies are limited per operation and parsed
off the event loop, Range numbers are bounded before conversion, and Location never comes from
the Host header. The same findings against a live `dgs serve`: test_api_door_live.py."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient
from service_harness import make_settings
from test_api_artifacts import RUN, add_artifacts
from test_api_assets import exr_bytes
from test_api_renders import finished

from service.app import create_app
from service.body import MAX_ERRORS

STUDIO = {"envmap": "builtin:studio"}
LIGHT = {"kind": "point", "position": [0, 0, 1]}


def _jobs(client) -> int:
    return len(client.get("/v1/jobs", params={"limit": 200}).json()["items"])


def _refused(r, path: str, status: int = 422) -> dict:
    assert r.status_code == status, r.text
    error = r.json()["error"]
    assert error["details"][0]["path"] == path, error
    return error


@pytest.mark.parametrize("params, path", [
    ({"checkpoint_every": True}, "params.checkpoint_every"),
    ({"checkpoint_every": "100"}, "params.checkpoint_every"),
    ({"gop": "5"}, "params.gop"),
    ({"gop": 5.0}, "params.gop"),
    ({"preset": 1}, "params.preset"),
    ({"frames": 0}, "params.frames"),
    ({"frames": "-99999999999999999999:"}, "params.frames"),
    ({"frames": "::0"}, "params.frames"),
    ({"frames": ""}, "params.frames"),
    ({"nope": 1}, "params.nope"),
])
def test_loose_job_params_are_refused_like_the_config(client, ready_capture, params, path):
    capture = ready_capture()
    before = _jobs(client)
    error = _refused(client.post("/v1/jobs", json={"capture_id": capture, "params": params}),
                     path)
    assert error["message"].startswith(f"{path}: ")
    assert _jobs(client) == before


@pytest.mark.parametrize("body, path", [
    ({**STUDIO, "rotation_deg": "90"}, "body.rotation_deg"),
    ({**STUDIO, "exposure": True}, "body.exposure"),
    ({**STUDIO, "orbit": True}, "body.orbit"),
    ({**STUDIO, "orbit": "8"}, "body.orbit"),
    ({**STUDIO, "orbit": 8.0}, "body.orbit"),
    ({**STUDIO, "ao": "yes"}, "body.ao"),
    ({**STUDIO, "ao": 1}, "body.ao"),
    ({**STUDIO, "fps": "24"}, "body.fps"),
    ({"lights": [{**LIGHT, "intensity": "2"}]}, "body.lights.0.intensity"),
    ({"lights": [{**LIGHT, "position": ["0", 0, 1]}]}, "body.lights.0.position.0"),
    ({**STUDIO, "frames": "-99999999999999999999:"}, "body.frames"),
    ({**STUDIO, "frames": "::0"}, "body.frames"),
    ({**STUDIO, "capture_light": "3"}, "body.capture_light"),
])
def test_loose_render_fields_are_refused(client, services, body, path):
    source = finished(services)
    before = _jobs(client)
    _refused(client.post("/v1/renders", json={"job_id": source, **body}), path)
    assert _jobs(client) == before


@pytest.mark.parametrize("body, path", [
    ({"fps": "24"}, "body.fps"),
    ({"fps": True}, "body.fps"),
    ({"position_tolerance": "0.001"}, "body.position_tolerance"),
    ({"formats": "stream"}, "body.formats"),
    ({"frames": "::0"}, "body.frames"),
    ({"frames": "-99999999999999999999:"}, "body.frames"),
])
def test_loose_export_fields_are_refused(client, services, body, path):
    source = finished(services)
    before = _jobs(client)
    _refused(client.post("/v1/exports", json={"job_id": source, **body}), path)
    assert _jobs(client) == before


def test_export_frames_are_checked_against_the_reconstruction(client, services, ready_capture):
    source = finished(services, capture_id=ready_capture())  # one frame
    before = _jobs(client)
    error = _refused(client.post("/v1/exports", json={"job_id": source, "frames": "5:9"}),
                     "frames")
    assert f"selects no frame of the 1 in the reconstruction {source}" in error["message"]
    assert _jobs(client) == before
    r = client.post("/v1/exports", json={"job_id": source, "frames": "0:1", "fps": 30})
    assert r.status_code == 202, r.text
    assert r.json()["params"]["fps"] == 30.0


@pytest.mark.parametrize("name", ["a\x00b", "\x1b[31mred", "two\r\nlines", "tab\there",
                                  "bidi\u202eevil", "line\u2028sep", "x" * 257])
def test_names_are_printable_and_bounded(client, services, ready_capture, name):
    capture = ready_capture()
    source = finished(services, capture_id=capture)
    for path, body in (("/v1/jobs", {"capture_id": capture}), ("/v1/renders", {
            "job_id": source, **STUDIO}), ("/v1/exports", {"job_id": source}),
            ("/v1/captures", {"format": "auto", "manifest": {"files": [
                {"path": "a", "size": 1, "sha256": "0" * 64}]}})):
        _refused(client.post(path, json={**body, "name": name}), "body.name")
    r = client.post("/v1/captures/archive", params={"name": name, "format": "auto"},
                    content=b"PK", headers={"Content-Type": "application/zip"})
    assert r.status_code == 422 and r.json()["error"]["details"][0]["path"] == "query.name"
    kept = "Studio B: take 3 – Ünïcode ✓"
    r = client.post("/v1/jobs", json={"capture_id": capture, "name": kept,
                                      "params": {"preset": "test"}})
    assert r.status_code == 202 and r.json()["name"] == kept


def test_json_bodies_are_limited_per_operation(tmp_path):
    settings = make_settings(tmp_path / "d", max_json_bytes=4096, max_manifest_bytes=65536)
    with TestClient(create_app(settings)) as client:
        big = json.dumps({"capture_id": "cap_x", "name": "x" * 5000})
        for path in ("/v1/jobs", "/v1/renders", "/v1/exports"):
            r = client.post(path, content=big, headers={"Content-Type": "application/json"})
            assert r.status_code == 413, r.text
            assert "limit of 4096 bytes" in r.json()["error"]["message"]

        def chunked():  # no Content-Length: counted as it arrives
            yield big[:3000].encode()
            yield big[3000:].encode()

        r = client.post("/v1/jobs", content=chunked(), headers={
            "Content-Type": "application/json"})
        assert r.status_code == 413, r.text
        files = [{"path": f"images/000000/cam{i:03d}.png", "size": 1, "sha256": "0" * 64}
                 for i in range(60)]  # about 6 kB: past the JSON limit, within the manifest's
        r = client.post("/v1/captures", json={"format": "auto", "manifest": {"files": files}})
        assert r.status_code == 201, r.text


def test_hostile_bodies_are_refused_before_they_are_parsed(client):
    headers = {"Content-Type": "application/json"}
    r = client.post("/v1/captures", content=b"[" + b"0," * 100_000 + b"0]", headers=headers)
    assert r.status_code == 422 and "expected a JSON object" in r.json()["error"]["message"]
    many = b'{"format": "auto", "manifest": {"files": [' + b"0," * 9_000_000 + b"0]}}"
    r = client.post("/v1/captures", content=many, headers=headers)
    assert r.status_code == 413 and "JSON values" in r.json()["error"]["message"], r.text
    bad = {"format": "auto", "manifest": {"files": [{"path": 1}] * 2}, "name": 5, "x": 1}
    r = client.post("/v1/captures", json=bad)
    details = r.json()["error"]["details"]
    assert r.status_code == 422 and len(details) <= MAX_ERRORS + 1, details
    bad = {"capture_id": "c", "params": {}, **{f"k{i}": i for i in range(200)}}
    details = client.post("/v1/jobs", json=bad).json()["error"]["details"]
    assert len(details) == MAX_ERRORS + 1
    assert details[-1]["message"] == f"{200 - MAX_ERRORS} more problems not listed"


@pytest.mark.parametrize("header, status, content", [
    ("bytes=" + "0" * 4400 + "-1", 206, slice(0, 2)),
    ("bytes=0-" + "9" * 5000, 206, slice(0, None)),
    ("bytes=" + "9" * 5000 + "-", 416, None),
    ("bytes=1" + "0" * 5000 + "-2" + "0" * 5000, 416, None),
    ("bytes=-" + "9" * 5000, 206, slice(0, None)),
    ("bytes=-" + "0" * 4400 + "10", 206, slice(-10, None)),
    ("bytes=\xb2-\xb3".encode("latin-1"), 200, slice(0, None)),  # not ASCII digits: ignored
])
def test_range_numbers_are_bounded_before_conversion(client, services, tmp_path, header,
                                                     status, content):
    job = services.store.create("local", "reconstruct", {}, capture_id=None)
    add_artifacts(services, job.id, RUN, tmp_path)
    blob = RUN["frames/000000/gaussians.ply"]
    r = client.post("/v1/assets?filename=sky.exr", content=exr_bytes(tmp_path))
    asset = r.json()
    exr = client.get(f"/v1/assets/{asset['id']}/content").content
    for url, data in ((f"/v1/jobs/{job.id}/artifacts/frames/000000/gaussians.ply", blob),
                      (f"/v1/assets/{asset['id']}/content", exr)):
        r = client.get(url, headers={"Range": header})
        assert r.status_code == status, r.text[:300]
        if content is not None:
            assert r.content == data[content]
        else:
            assert r.headers["Content-Range"] == f"bytes */{len(data)}"
            assert len(r.json()["error"]["message"]) < 200


def test_header_numbers_are_bounded(client, services):
    job = finished(services)
    r = client.get(f"/v1/jobs/{job}/events", headers={"Last-Event-ID": "\xb2".encode("latin-1")})
    assert r.status_code == 400, r.text
    r = client.post("/v1/uploads", headers={"Tus-Resumable": "1.0.0",
                                            "Upload-Length": "9" * 5000})
    assert r.status_code == 400 and "at most 18 digits" in r.json()["error"]["message"]


def test_location_is_relative_or_under_the_public_url(tmp_path, client, services, ready_capture):
    capture = ready_capture()
    evil = {"Host": "evil.example", "X-Forwarded-Host": "evil.example"}
    r = client.post("/v1/jobs", json={"capture_id": capture, "params": {"preset": "test"}},
                    headers=evil)
    assert r.status_code == 202 and r.headers["Location"] == f"/v1/jobs/{r.json()['id']}"
    settings = make_settings(tmp_path / "public", public_url="https://dgs.example.com/")
    with TestClient(create_app(settings)) as other:
        r = other.post("/v1/assets?filename=sky.exr", content=exr_bytes(tmp_path), headers=evil)
        assert r.headers["Location"] == f"https://dgs.example.com/v1/assets/{r.json()['id']}"


def test_json_forms_are_taken_strictly(client, services, ready_capture):
    """Strict, yet JSON's own forms: a list for a tuple, an ISO string for a time (together: a
    validator that handed the body back as Python would refuse the time)."""
    source = finished(services, capture_id=ready_capture())
    r = client.post("/v1/renders", json={
        "job_id": source, "expires_at": "2099-01-01T00:00:00Z", "lights": [
            {"kind": "point", "position": [0, 0, 1], "color": [1, 0.5, 0], "intensity": 2}]})
    assert r.status_code == 202, r.text
    assert r.json()["params"]["lights"][0]["position"] == [0, 0, 1]
    r = client.post("/v1/exports", json={"job_id": source, "expires_at": "2099-01-01T00:00:00Z",
                                         "formats": ["spz"]})
    assert r.status_code == 202, r.text
