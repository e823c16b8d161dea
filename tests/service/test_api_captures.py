"""/v1/captures: manifests (every unsafe path refused), file states, commit (validation with
core.data, freeze into the artifact store), amendments, deletion."""

from __future__ import annotations

import hashlib

import pytest
from service_harness import capture_files, upload_file
from sqlalchemy import func, select

from worker.models import Capture

SHA = "0" * 64


def _count(services) -> int:
    with services.store.session(write=False) as s:
        return s.scalar(select(func.count()).select_from(Capture))


@pytest.mark.parametrize("path", [
    "../x.png", "images/../../x.png", "/etc/passwd", "C:/x.png", "images\\cam.png",
    "images//cam.png", "./capture.json", "images/./cam.png", "images/cam\x00.png",
    "images/cam\n.png", "images/" + "a" * 300 + ".png", "images/" + "d/" * 600 + "x.png"])
def test_unsafe_manifest_paths_are_refused(client, services, path):
    r = client.post("/v1/captures", json={"format": "auto", "manifest": {"files": [
        {"path": "capture.json", "size": 2, "sha256": SHA}, {"path": path, "size": 1,
                                                             "sha256": SHA}]}})
    assert r.status_code in (400, 422), r.text
    error = r.json()["error"]
    assert error["code"] == "invalid_request" and error["message"]
    assert _count(services) == 0


@pytest.mark.parametrize("files, words", [
    ([("capture.json", 2), ("capture.json", 2)], "listed twice"),
    ([("images/a", 2), ("images/a/b.png", 2)], "as a file and as a folder"),
    ([("gt/depth.npy", 2)], "not part of a canonical capture"),
    ([("images", 2)], "not part of a canonical capture"),
])
def test_manifest_consistency(client, services, files, words):
    r = client.post("/v1/captures", json={"format": "canonical", "manifest": {"files": [
        {"path": p, "size": n, "sha256": SHA} for p, n in files]}})
    assert r.status_code == 422 and words in r.json()["error"]["message"], r.text
    assert r.json()["error"]["details"]
    assert _count(services) == 0


def test_other_formats_accept_any_safe_path(client):
    r = client.post("/v1/captures", json={"format": "auto", "manifest": {"files": [
        {"path": "gt/depth.npy", "size": 2, "sha256": SHA.upper()}]}})
    assert r.status_code == 201
    listing = client.get(r.json()["links"]["files"]).json()
    assert listing["items"][0]["sha256"] == SHA  # stored in lower case


@pytest.mark.parametrize("entry", [
    {"path": "capture.json", "size": -1, "sha256": SHA},
    {"path": "capture.json", "size": 1, "sha256": "xyz"},
    {"path": "capture.json", "size": 1},
])
def test_malformed_entries_are_422(client, services, entry):
    r = client.post("/v1/captures", json={"format": "canonical", "manifest": {"files": [entry]}})
    assert r.status_code == 422 and r.json()["error"]["details"][0]["path"].startswith("body")
    assert _count(services) == 0


def test_limits(tmp_path):
    from fastapi.testclient import TestClient
    from service_harness import make_settings

    from service.app import create_app

    settings = make_settings(tmp_path / "d", max_file_bytes=100, max_capture_bytes=150,
                             max_capture_files=3, max_manifest_bytes=4096)
    client = TestClient(create_app(settings))

    def post(files):
        return client.post("/v1/captures", json={"format": "auto", "manifest": {"files": [
            {"path": f"f{i}", "size": n, "sha256": SHA} for i, n in enumerate(files)]}})

    assert post([101]).status_code == 422  # one file over the per-file limit
    r = post([100, 60])
    assert r.status_code == 413 and "150" in r.json()["error"]["message"]
    assert post([1, 1, 1, 1]).status_code == 413
    assert post([1] * 200).status_code == 413  # a body over max_manifest_bytes
    assert post([100, 50]).status_code == 201
    info = client.get("/v1/info").json()["limits"]
    assert info["max_file_bytes"] == 100 and info["max_capture_files"] == 3


def test_expiry(client, new_capture):
    r = client.post("/v1/captures", json={"format": "auto", "expires_at": "2000-01-01T00:00:00Z",
                                          "manifest": {"files": [{"path": "a", "size": 1,
                                                                  "sha256": SHA}]}})
    assert r.status_code == 422 and "past" in r.json()["error"]["message"]
    r = client.post("/v1/captures", json={"format": "auto", "expires_at": "2999-01-01T00:00:00",
                                          "manifest": {"files": [{"path": "a", "size": 1,
                                                                  "sha256": SHA}]}})
    assert r.status_code == 422  # a time without a zone is ambiguous
    capture = new_capture({"a": b"x"}, fmt="auto", expires_at="2999-01-01T00:00:00+01:00")
    assert capture["expires_at"] == "2998-12-31T23:00:00Z"
    assert new_capture({"a": b"x"}, fmt="auto")["expires_at"] is None


@pytest.mark.parametrize("database_url", ["sqlite", "postgres"], indirect=True)
def test_upload_commit_freezes_a_valid_capture(client, services, new_capture, synth_capture):
    files = capture_files(synth_capture)
    capture = new_capture(files, name="synthetic")
    assert capture["state"] == "uploading" and capture["files"]["missing"] == len(files)
    assert client.post(f"/v1/captures/{capture['id']}/commit").status_code == 409
    for path, data in files.items():
        upload_file(client, capture["id"], path, data)
    r = client.post(f"/v1/captures/{capture['id']}/commit")
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["state"] == "ready" and out["committed_at"] and out["error"] is None
    assert out["summary"] == {"frames": 1, "cameras": 8, "views": 8, "masks": 8, "normals": 0,
                              "camera_ids": [f"cam{i:02d}" for i in range(8)],
                              "image_sizes": [{"width": 32, "height": 32, "cameras": 8}],
                              "source_format": "canonical", "test_cameras": None,
                              "import_warnings": []}
    assert out["files"]["received"] == len(files) and out["files"]["missing"] == 0
    assert not services.staging.capture_dir(capture["id"]).exists()
    stored = {b.key for b in services.blobs.list(f"captures/{capture['id']}")}
    assert stored == {f"captures/{capture['id']}/{p}" for p in files}
    root = services.blobs.local_path(f"captures/{capture['id']}")
    assert all((root / p).read_bytes() == d for p, d in files.items())
    assert client.post(f"/v1/captures/{capture['id']}/commit").status_code == 200  # idempotent
    page = client.get("/v1/captures?state=ready").json()
    assert [c["id"] for c in page["items"]] == [capture["id"]]


def test_missing_files_are_listed(client, new_capture, synth_capture):
    files = capture_files(synth_capture)
    capture = new_capture(files)
    upload_file(client, capture["id"], "capture.json", files["capture.json"])
    r = client.post(f"/v1/captures/{capture['id']}/commit")
    assert r.status_code == 409
    error = r.json()["error"]
    assert error["code"] == "files_missing"
    assert {d["path"] for d in error["details"]} == set(files) - {"capture.json"}
    assert client.get(f"/v1/captures/{capture['id']}").json()["state"] == "uploading"
    page = client.get(f"/v1/captures/{capture['id']}/files?state=missing&limit=5").json()
    assert len(page["items"]) == 5 and page["next_cursor"]
    rest = client.get(f"/v1/captures/{capture['id']}/files?state=missing&limit=100&cursor="
                      f"{page['next_cursor']}").json()
    assert len(page["items"]) + len(rest["items"]) == len(files) - 1
    assert rest["next_cursor"] is None
    received = client.get(f"/v1/captures/{capture['id']}/files?state=received").json()
    assert [f["path"] for f in received["items"]] == ["capture.json"]
    assert client.get(f"/v1/captures/{capture['id']}/files?cursor=junk").status_code == 400


def test_invalid_capture_is_422_and_can_be_fixed(client, services, new_capture, synth_capture):
    files = capture_files(synth_capture)
    broken = dict(files)
    broken["images/000000/cam03.png"] = b"not a png at all"
    capture = new_capture(broken)
    for path, data in broken.items():
        upload_file(client, capture["id"], path, data)
    r = client.post(f"/v1/captures/{capture['id']}/commit")
    assert r.status_code == 422
    error = r.json()["error"]
    assert error["code"] == "invalid_capture" and "images/000000/cam03.png" in error["message"]
    assert [d["path"] for d in error["details"]] == ["images/000000/cam03.png"]
    out = client.get(f"/v1/captures/{capture['id']}").json()
    assert out["state"] == "uploading" and out["error"]["code"] == "invalid_capture"
    assert out["files"]["received"] == len(files)  # nothing was deleted
    assert services.blobs.list(f"captures/{capture['id']}") == []
    good = files["images/000000/cam03.png"]
    r = client.patch(f"/v1/captures/{capture['id']}/manifest", json={"files": [
        {"path": "images/000000/cam03.png", "size": len(good),
         "sha256": hashlib.sha256(good).hexdigest()}]})
    assert r.status_code == 200 and r.json()["files"]["missing_paths"] == [
        "images/000000/cam03.png"]
    upload_file(client, capture["id"], "images/000000/cam03.png", good)
    r = client.post(f"/v1/captures/{capture['id']}/commit")
    assert r.status_code == 200 and r.json()["error"] is None


def test_not_a_capture_is_422(client, new_capture):
    files = {"notes.txt": b"hello"}
    capture = new_capture(files, fmt="auto")
    upload_file(client, capture["id"], "notes.txt", files["notes.txt"])
    r = client.post(f"/v1/captures/{capture['id']}/commit")
    assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_capture"
    assert "no known format" in r.json()["error"]["message"]


def test_amendments(client, new_capture):
    capture = new_capture({"a": b"1", "b": b"2"}, fmt="auto")
    url = f"/v1/captures/{capture['id']}/manifest"
    r = client.patch(url, json={"remove": ["zzz"]})
    assert r.status_code == 422
    r = client.patch(url, json={"remove": ["b"], "files": [{"path": "c", "size": 3,
                                                             "sha256": SHA}]})
    assert r.status_code == 200
    out = r.json()
    assert out["files"]["declared"] == 2 and out["total_bytes"] == 4
    assert client.patch(url, json={"files": [{"path": "../c", "size": 3,
                                              "sha256": SHA}]}).status_code == 422


def test_delete_capture(client, services, ready_capture):
    capture_id = ready_capture()
    assert services.blobs.list(f"captures/{capture_id}")
    assert client.delete(f"/v1/captures/{capture_id}").status_code == 204
    assert client.get(f"/v1/captures/{capture_id}").status_code == 404
    assert services.blobs.list(f"captures/{capture_id}") == []
    assert client.delete(f"/v1/captures/{capture_id}").status_code == 404


def test_capture_in_use_cannot_be_deleted(client, ready_capture):
    capture_id = ready_capture()
    job = client.post("/v1/jobs", json={"capture_id": capture_id, "params": {"preset": "test"}})
    assert job.status_code == 202
    r = client.delete(f"/v1/captures/{capture_id}")
    assert r.status_code == 409 and job.json()["id"] in r.json()["error"]["message"]
    assert client.post(f"/v1/jobs/{job.json()['id']}/cancel").status_code == 202
    assert client.delete(f"/v1/captures/{capture_id}").status_code == 204
    assert client.get(f"/v1/jobs/{job.json()['id']}").json()["capture_id"] is None


def test_an_interrupted_commit_goes_back_to_uploading(settings, client, new_capture):
    from sqlalchemy import update

    from service.app import create_app

    capture = new_capture({"a": b"1"}, fmt="auto")
    services = client.app.state.services
    with services.store.session() as s:  # a process died while it validated
        s.execute(update(Capture).where(Capture.id == capture["id"]).values(
            state="committing", summary={"commit_owner": "elsewhere/1/1/x"}))
    create_app(settings)  # this host is not "elsewhere": its state is left alone
    assert client.get(f"/v1/captures/{capture['id']}").json()["state"] == "committing"
    with services.store.session() as s:
        s.execute(update(Capture).where(Capture.id == capture["id"]).values(summary=None))
    create_app(settings)
    out = client.get(f"/v1/captures/{capture['id']}").json()
    assert out["state"] == "uploading" and out["error"]["code"] == "commit_interrupted"


def test_listing_pages(client, new_capture):
    ids = [new_capture({"a": b"1"}, fmt="auto")["id"] for _ in range(5)]
    seen, cursor = [], None
    while True:
        page = client.get("/v1/captures", params={"limit": 2, **({"cursor": cursor}
                                                                 if cursor else {})}).json()
        seen += [c["id"] for c in page["items"]]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == ids[::-1]


def test_a_long_commit_answers_202_and_finishes_in_the_background(client, services, new_capture,
                                                                  synth_capture, monkeypatch):
    import threading

    import service.upload.commit

    services.settings.commit_wait_seconds = 0.2
    files = capture_files(synth_capture)
    capture = new_capture(files)
    for path, data in files.items():
        upload_file(client, capture["id"], path, data)
    proceed, summarize = threading.Event(), service.upload.commit.summarize

    def slow_summary(*args):
        assert proceed.wait(30)
        return summarize(*args)

    monkeypatch.setattr(service.upload.commit, "summarize", slow_summary)  # validation takes long
    r = client.post(f"/v1/captures/{capture['id']}/commit")
    assert r.status_code == 202 and r.json()["state"] == "committing"
    assert client.post(f"/v1/captures/{capture['id']}/commit").status_code == 202
    assert client.delete(f"/v1/captures/{capture['id']}").status_code == 409
    done = services.committer.running(capture["id"])
    proceed.set()
    assert done.wait(30)
    assert client.get(f"/v1/captures/{capture['id']}").json()["state"] == "ready"


def test_default_retention(tmp_path):
    import datetime as dt

    from fastapi.testclient import TestClient
    from service_harness import make_settings

    from service.app import create_app

    client = TestClient(create_app(make_settings(tmp_path / "d", retention_days=2)))
    r = client.post("/v1/captures", json={"format": "auto", "manifest": {"files": [
        {"path": "a", "size": 1, "sha256": SHA}]}})
    expires = dt.datetime.fromisoformat(r.json()["expires_at"])
    left = expires - dt.datetime.now(dt.UTC)
    assert dt.timedelta(days=1, hours=23) < left <= dt.timedelta(days=2)


def test_canonical_points_ply_is_uploaded_checked_and_kept(client, services, new_capture,
                                                          synth_capture, tmp_path):
    import numpy as np

    from core.data.points import PointCloud, write_points_ply

    write_points_ply(tmp_path / "points.ply", PointCloud(np.random.default_rng(0).normal(
        size=(40, 3))))
    files = {**capture_files(synth_capture), "points.ply": (tmp_path / "points.ply").read_bytes()}
    broken = {**files, "points.ply": b"ply\nformat ascii 1.0\nend_header\n"}
    for content, ok in ((broken, False), (files, True)):
        capture = new_capture(content)
        for path, data in content.items():
            upload_file(client, capture["id"], path, data)
        r = client.post(f"/v1/captures/{capture['id']}/commit")
        if not ok:  # the problem names the file; the capture stays uploading
            assert r.status_code == 422, r.text
            error = r.json()["error"]
            assert error["code"] == "invalid_capture" and "points.ply" in error["message"]
            assert "no 'vertex' element" in error["message"]
            continue
        assert r.status_code == 200 and r.json()["state"] == "ready", r.text
        root = services.blobs.local_path(f"captures/{capture['id']}")
        assert (root / "points.ply").read_bytes() == files["points.ply"]
