"""The artifact store on a local folder and on an S3-compatible server (moto's, over HTTP):
the same behaviour, and keys that could escape their folder refused before any I/O."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from worker.blobs import LocalBlobStore, S3BlobStore, check_key, open_store


@pytest.fixture(scope="module")
def s3_endpoint():
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0)
    server.start()
    host, port = server.get_host_and_port()
    yield f"http://{host}:{port}"
    server.stop()


@pytest.fixture(params=["local", "s3"])
def blobs(request, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    if request.param == "local":
        return LocalBlobStore(tmp_path / "store")
    endpoint = request.getfixturevalue("s3_endpoint")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "test")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "test")
    import boto3

    bucket = f"b-{tmp_path.name.lower().replace('_', '-')[-40:]}"
    boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1").create_bucket(Bucket=bucket)
    return open_store(f"s3://{bucket}/deploy-a", endpoint_url=endpoint, region="us-east-1")


def test_round_trip_list_range_delete(blobs, tmp_path: Path):
    data = bytes(range(256)) * 5000  # 1.28 MB: more than one read chunk
    src = tmp_path / "src.bin"
    src.write_bytes(data)
    blobs.put_file("jobs/j1/artifacts/frames/000000/gaussians.ply", src)
    blobs.put_file("jobs/j1/artifacts/eval.json", src)
    blobs.put_file("jobs/j10/artifacts/eval.json", src)  # a sibling with a common prefix
    assert blobs.size("jobs/j1/artifacts/eval.json") == len(data)
    assert blobs.size("jobs/j1/nothing") is None
    assert [(b.key, b.size) for b in blobs.list("jobs/j1")] == [
        ("jobs/j1/artifacts/eval.json", len(data)),
        ("jobs/j1/artifacts/frames/000000/gaussians.ply", len(data))]
    key = "jobs/j1/artifacts/eval.json"
    assert b"".join(blobs.read_range(key, 0, len(data))) == data
    assert b"".join(blobs.read_range(key, 1_000_000, 1_000_010)) == data[1_000_000:1_000_010]
    assert b"".join(blobs.read_range(key, 5, 5)) == b""
    out = tmp_path / "out" / "copy.bin"
    blobs.get_file(key, out)
    assert out.read_bytes() == data and not out.with_name("copy.bin.part").exists()
    with pytest.raises(FileNotFoundError):
        blobs.get_file("jobs/j1/missing", tmp_path / "x")
    assert blobs.delete_prefix("jobs/j1") == 2
    assert blobs.list("jobs/j1") == [] and blobs.size("jobs/j10/artifacts/eval.json")


@pytest.mark.parametrize("key", ["", "/etc/passwd", "a/../b", "../x", "a//b", "a/./b",
                                 "a\\b", "a/b\x00", "a/"])
def test_keys_that_escape_are_refused(key: str, tmp_path: Path):
    with pytest.raises(ValueError, match="key"):
        check_key(key)
    store = LocalBlobStore(tmp_path)
    with pytest.raises(ValueError):
        store.put_file(key, tmp_path / "none")
    with pytest.raises(ValueError):
        S3BlobStore("bucket", client=object()).size(key)


def test_store_urls(tmp_path: Path):
    assert isinstance(open_store(tmp_path.as_uri()), LocalBlobStore)
    with pytest.raises(ValueError, match="bucket"):
        open_store("s3:///nothing")
    with pytest.raises(ValueError, match="file:///folder or s3://"):
        open_store("ftp://host/x")


def test_two_fetches_of_one_file_at_once_both_end_whole(blobs, tmp_path: Path):
    """Two jobs on one machine fetch the same capture file at the same moment: each download
    has a temporary of its own, so neither renames the other's away (a FileNotFoundError that
    failed one of the jobs) and the file ends whole. Threads stand in for the pool processes."""
    data = bytes(range(256)) * 4000
    src = tmp_path / "src.bin"
    src.write_bytes(data)
    blobs.put_file("captures/c1/images/000000/cam00.png", src)
    dest = tmp_path / "scratch" / "cam00.png"
    start, errors = threading.Barrier(6), []

    def fetch() -> None:
        start.wait()
        for _ in range(15):
            try:
                blobs.get_file("captures/c1/images/000000/cam00.png", dest)
            except Exception as exc:  # noqa: BLE001  (collected and shown below)
                errors.append(exc)

    threads = [threading.Thread(target=fetch) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and dest.read_bytes() == data
    assert [p.name for p in dest.parent.iterdir()] == ["cam00.png"]  # no temporary left
