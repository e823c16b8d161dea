"""Helpers of the API tests (a module with its own name: several test folders have a conftest,
so `from conftest import ...` would pick whichever was imported first)."""

from __future__ import annotations

import base64
import hashlib
import json
import io
import threading
import zipfile
from pathlib import Path

import httpx
from fastapi.testclient import TestClient

from service.settings import ServiceSettings

TUS = {"Tus-Resumable": "1.0.0"}
ZIP = {"Content-Type": "application/zip"}
CANONICAL = ("capture.json", "images/", "masks/", "normals/")


def make_zip(files: dict[str, bytes], prefix: str = "",
             method: int = zipfile.ZIP_DEFLATED) -> bytes:
    """A zip archive of {path: bytes}, each path under `prefix`."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as zf:
        for path, data in files.items():
            zf.writestr(prefix + path, data)
    return buf.getvalue()


def make_settings(data_dir: Path, **overrides) -> ServiceSettings:
    """Settings that ignore the developer's DGS_* environment."""
    fields = {"data_dir": data_dir, "database_url": None, "broker_url": None,
              "storage_url": None, "public_url": None, "retention_days": None,
              "queue": "dgs-test", "commit_wait_seconds": 30.0, "sse_poll_seconds": 0.05,
              "devices": "auto,cpu", "normal_estimators": {}}
    fields.update(overrides)
    return ServiceSettings(_env_file=None, **fields)



def capture_files(root: Path) -> dict[str, bytes]:
    """The canonical content of a capture folder: path -> bytes."""
    out = {}
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = path.relative_to(root).as_posix()
        if rel.startswith(CANONICAL):
            out[rel] = path.read_bytes()
    return out


def capture_variant(root: Path, *, cameras: int | None = None,
                    masks: bool = True) -> dict[str, bytes]:
    """The canonical content of the capture at `root` with only its first `cameras` cameras
    (None: all), and without its masks unless `masks`."""
    files = capture_files(root)
    doc = json.loads(files["capture.json"])
    if cameras is not None:
        doc["cameras"] = doc["cameras"][:cameras]
        doc.pop("test_cameras", None)
        kept = {c["id"] for c in doc["cameras"]}
        files = {p: b for p, b in files.items() if p == "capture.json" or Path(p).stem in kept}
    if not masks:
        files = {p: b for p, b in files.items() if not p.startswith("masks/")}
    files["capture.json"] = json.dumps(doc).encode()
    return files


def manifest_of(files: dict[str, bytes]) -> dict:
    return {"files": [{"path": p, "size": len(b), "sha256": hashlib.sha256(b).hexdigest()}
                      for p, b in files.items()]}


def metadata(**values: str) -> str:
    return ",".join(f"{k} {base64.b64encode(v.encode()).decode()}" for k, v in values.items())


def tus_create(client: TestClient, capture_id: str, path: str, length: int,
               headers: dict | None = None):
    return client.post("/v1/uploads", headers={
        **TUS, **(headers or {}), "Upload-Length": str(length),
        "Upload-Metadata": metadata(capture=capture_id, path=path)})


def tus_patch(client: TestClient, url: str, offset: int, data: bytes,
              headers: dict | None = None):
    return client.patch(url, content=data, headers={
        **TUS, **(headers or {}), "Upload-Offset": str(offset),
        "Content-Type": "application/offset+octet-stream"})


def upload_file(client: TestClient, capture_id: str, path: str, data: bytes,
                headers: dict | None = None) -> None:
    created = tus_create(client, capture_id, path, len(data), headers)
    assert created.status_code == 201, created.text
    if data:
        done = tus_patch(client, created.headers["Location"], 0, data, headers)
        assert done.status_code == 204, done.text


def submit_together(url: str, path: str, body: dict, key: str,
                    n: int = 8) -> list[httpx.Response]:
    """`n` POSTs of `body` to `path` of the server at `url` with one Idempotency-Key, each on
    its own connection and thread, released together by a barrier; their answers."""
    start, answers = threading.Barrier(n), []

    def submit() -> None:
        with httpx.Client(base_url=url, timeout=120) as http:
            start.wait()
            answers.append(http.post(path, json=body, headers={"Idempotency-Key": key}))

    threads = [threading.Thread(target=submit) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return answers
