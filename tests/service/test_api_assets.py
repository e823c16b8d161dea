"""/v1/assets: environment maps, checked before they are kept (renders that use them:
test_api_renders.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from service_harness import make_settings

from core.data.images import write_exr
from service.app import create_app


def exr_bytes(tmp_path: Path, width: int = 32, height: int = 16, nan: bool = False) -> bytes:
    image = np.random.default_rng(0).random((height, width, 3), dtype=np.float32) * 4
    if nan:
        image[3, 5, 1] = np.nan
    path = tmp_path / "map.exr"
    write_exr(path, image)
    return path.read_bytes()


def hdr_bytes(tmp_path: Path, width: int = 32, height: int = 16) -> bytes:
    import cv2

    path = tmp_path / "map.hdr"
    assert cv2.imwrite(str(path), np.full((height, width, 3), 0.5, np.float32))
    return path.read_bytes()


def stored(services) -> list:
    return services.blobs.list("assets")


def test_envmap_upload_and_download(client, services, tmp_path):
    body = exr_bytes(tmp_path)
    r = client.post("/v1/assets?kind=envmap&filename=studio.exr", content=body)
    assert r.status_code == 201, r.text
    asset = r.json()
    assert (asset["width"], asset["height"], asset["channels"]) == (32, 16, 3)
    assert asset["content_type"] == "image/x-exr" and asset["size"] == len(body)
    assert r.headers["Location"].endswith(asset["links"]["self"])
    assert client.get(asset["links"]["content"]).content == body
    part = client.get(asset["links"]["content"], headers={"Range": "bytes=0-3"})
    assert part.status_code == 206 and part.content == body[:4]
    assert [a["id"] for a in client.get("/v1/assets").json()["items"]] == [asset["id"]]
    hdr = client.post("/v1/assets?filename=sky.hdr", content=hdr_bytes(tmp_path))
    assert hdr.status_code == 201 and hdr.json()["content_type"] == "image/vnd.radiance"
    assert client.delete(asset["links"]["self"]).status_code == 204
    assert client.get(asset["links"]["self"]).status_code == 404
    assert len(stored(services)) == 1


@pytest.mark.parametrize("filename, make, words", [
    ("wide.exr", lambda t: exr_bytes(t, 30, 16), "twice as wide"),
    ("nan.exr", lambda t: exr_bytes(t, nan=True), "NaN or Inf"),
    ("junk.exr", lambda t: b"\x76\x2f\x31\x01 junk", "OpenEXR"),
    ("junk.hdr", lambda t: b"P6 not radiance", "Radiance"),
    ("square.hdr", lambda t: hdr_bytes(t, 16, 16), "twice as wide"),
    ("map.png", lambda t: b"png", "filename"),
    ("../../evil.exr", lambda t: b"x", "filename"),
])
def test_bad_envmaps_are_refused_and_not_kept(client, services, tmp_path, filename, make, words):
    r = client.post("/v1/assets", params={"filename": filename}, content=make(tmp_path))
    assert r.status_code == 422 and words in r.json()["error"]["message"], r.text
    assert stored(services) == [] and client.get("/v1/assets").json()["items"] == []
    assert list(services.staging.tmp_dir().iterdir()) == []


def test_asset_size_limit(tmp_path):
    client = TestClient(create_app(make_settings(tmp_path / "d", max_asset_bytes=1000)))
    r = client.post("/v1/assets?filename=big.exr", content=exr_bytes(tmp_path, 64, 32))
    assert r.status_code == 413
    assert client.app.state.services.blobs.list("assets") == []
