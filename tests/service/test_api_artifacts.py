"""/v1/jobs/{id}/artifacts: typed listing, downloads with HTTP Range / ETag / If-Range, and the
whole set as one streamed zip."""

from __future__ import annotations

import hashlib
import io
import zipfile

import pytest

from core.rundir import classify

BLOB = bytes(range(256)) * 4  # 1024 bytes
RUN = {"frames/000000/gaussians.ply": BLOB, "frames/000001/gaussians.ply": BLOB[:100],
       "renders/000000/cam00_rgb.png": b"png" * 10, "renders/000001/cam00_rgb.png": b"p",
       "metrics.json": b'{"psnr": 30}'}


def add_artifacts(services, job_id: str, files: dict[str, bytes], tmp_path) -> None:
    for rel, data in files.items():
        src = tmp_path / "src.bin"
        src.write_bytes(data)
        services.blobs.put_file(f"jobs/{job_id}/artifacts/{rel}", src)
        kind = classify(rel)
        services.store.add_artifact(job_id, rel, kind=kind.kind, size=len(data),
                                    sha256=hashlib.sha256(data).hexdigest(),
                                    content_type=kind.content_type, frame=kind.frame)


@pytest.fixture
def job_id(services, tmp_path) -> str:
    job = services.store.create("local", "reconstruct", {}, capture_id=None)
    add_artifacts(services, job.id, RUN, tmp_path)
    return job.id


def test_typed_listing(client, job_id):
    url = f"/v1/jobs/{job_id}/artifacts"
    items = client.get(url).json()["items"]
    assert [a["path"] for a in items] == sorted(RUN)
    ply = items[0]
    assert ply["kind"] == "ply" and ply["frame"] == "000000" and ply["size"] == len(BLOB)
    assert ply["sha256"] == hashlib.sha256(BLOB).hexdigest()
    assert ply["url"].endswith(f"/v1/jobs/{job_id}/artifacts/frames/000000/gaussians.ply")
    renders = client.get(url, params={"kind": "render"}).json()["items"]
    assert [a["path"] for a in renders] == ["renders/000000/cam00_rgb.png",
                                             "renders/000001/cam00_rgb.png"]
    one = client.get(url, params={"kind": "render", "frame": "000001"}).json()["items"]
    assert [a["path"] for a in one] == ["renders/000001/cam00_rgb.png"]
    first = client.get(url, params={"limit": 2}).json()
    second = client.get(url, params={"limit": 10, "cursor": first["next_cursor"]}).json()
    assert [a["path"] for a in first["items"] + second["items"]] == sorted(RUN)
    assert second["next_cursor"] is None


def test_download_whole_and_etag(client, job_id):
    url = f"/v1/jobs/{job_id}/artifacts/frames/000000/gaussians.ply"
    r = client.get(url)
    assert r.status_code == 200 and r.content == BLOB
    assert r.headers["Accept-Ranges"] == "bytes" and r.headers["Content-Length"] == "1024"
    assert r.headers["content-type"] == "application/x-ply"
    etag = r.headers["ETag"]
    assert etag == f'"{hashlib.sha256(BLOB).hexdigest()}"'
    assert client.get(url, headers={"If-None-Match": etag}).status_code == 304
    assert client.get(url, headers={"If-None-Match": '"other"'}).status_code == 200
    head = client.head(url)
    assert head.status_code == 200 and head.headers["Content-Length"] == "1024"
    assert head.content == b""


@pytest.mark.parametrize("header, start, end", [
    ("bytes=0-99", 0, 100), ("bytes=1000-", 1000, 1024), ("bytes=-24", 1000, 1024),
    ("bytes=1000-5000", 1000, 1024), ("bytes=-5000", 0, 1024), ("bytes=1023-1023", 1023, 1024),
])
def test_single_ranges(client, job_id, header, start, end):
    r = client.get(f"/v1/jobs/{job_id}/artifacts/frames/000000/gaussians.ply",
                   headers={"Range": header})
    assert r.status_code == 206 and r.content == BLOB[start:end]
    assert r.headers["Content-Range"] == f"bytes {start}-{end - 1}/1024"
    assert r.headers["Content-Length"] == str(end - start)


@pytest.mark.parametrize("header", ["bytes=1024-", "bytes=5000-6000", "bytes=-0"])
def test_unsatisfiable_ranges(client, job_id, header):
    r = client.get(f"/v1/jobs/{job_id}/artifacts/frames/000000/gaussians.ply",
                   headers={"Range": header})
    assert r.status_code == 416 and r.headers["Content-Range"] == "bytes */1024"
    assert r.json()["error"]["code"] == "range_not_satisfiable"


@pytest.mark.parametrize("header", ["bytes=0-1,5-6", "bytes=9-3", "items=0-1", "bytes=x-y"])
def test_ranges_that_are_ignored(client, job_id, header):
    r = client.get(f"/v1/jobs/{job_id}/artifacts/frames/000000/gaussians.ply",
                   headers={"Range": header})
    assert r.status_code == 200 and r.content == BLOB


def test_if_range(client, job_id):
    url = f"/v1/jobs/{job_id}/artifacts/frames/000000/gaussians.ply"
    etag = client.head(url).headers["ETag"]
    r = client.get(url, headers={"Range": "bytes=10-19", "If-Range": etag})
    assert r.status_code == 206 and r.content == BLOB[10:20]
    r = client.get(url, headers={"Range": "bytes=10-19", "If-Range": '"stale"'})
    assert r.status_code == 200 and r.content == BLOB


def test_unknown_paths_never_touch_the_file_system(client, job_id, services):
    for path in ["nope.ply", "frames/%2e%2e/metrics.json", "frames%2F..%2Fmetrics.json",
                 "%2e%2e/%2e%2e/dgs.sqlite3"]:
        r = client.get(f"/v1/jobs/{job_id}/artifacts/{path}")
        assert r.status_code == 404, path
    assert client.get(f"/v1/jobs/job_nope/artifacts/metrics.json").status_code == 404


def test_all_artifacts_as_one_zip(client, job_id):
    r = client.get(f"/v1/jobs/{job_id}/artifacts.zip")
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        assert zf.testzip() is None
        assert {i.filename: zf.read(i) for i in zf.infolist()} == RUN
        assert all(i.compress_type == zipfile.ZIP_STORED for i in zf.infolist())
