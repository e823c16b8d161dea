"""Captures and assets sent to the API: the manifest, resumable tus uploads of each file, the
commit; environment maps."""

from __future__ import annotations

import base64
import hashlib
import json
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx

from core.files import sha256_file
from service.client.http import ApiError, Http

__all__ = ["Uploads", "manifest_of"]

CHUNK = 8 << 20
"""Bytes per tus PATCH when each carries a checksum (Client chunk_checksum)."""
CANONICAL = ("capture.json", "images/", "masks/", "normals/")
"""What a canonical capture holds (docs/design.md 3.1); anything else in its folder (a synthetic
capture's ground truth, notes) stays on the client."""


def _blocks(f, length: int, start: int,
            progress: Callable[[int], None] | None) -> Iterator[bytes]:
    """`length` bytes of `f` from where it stands, in blocks of 1 MiB (a streamed body)."""
    sent = 0
    while sent < length:
        block = f.read(min(1 << 20, length - sent))
        if not block:
            raise ValueError(f"{f.name} became shorter while it was uploaded")
        yield block
        sent += len(block)
        if progress is not None:
            progress(start + sent)


def manifest_of(folder: str | os.PathLike[str], format: str = "canonical") -> list[dict]:
    """[{path, size, sha256}] of the files under `folder` that a capture of `format` sends:
    for canonical, capture.json, images/, masks/ and normals/; otherwise every file. Hidden
    files are left out."""
    root = Path(folder)
    if not root.is_dir():
        raise ValueError(f"folder: {root} is not a directory")
    out = []
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if (not p.is_file() or any(part.startswith(".") for part in rel.split("/"))
                or (format == "canonical" and not rel.startswith(CANONICAL))):
            continue
        out.append({"path": rel, "size": p.stat().st_size, "sha256": sha256_file(p)})
    if not out:
        raise ValueError(f"folder: {root} has no file to upload as a {format} capture")
    return out


class Uploads(Http):
    """Captures (manifest, tus uploads, commit) and assets."""

    # -- captures -----------------------------------------------------------------------------
    def create_capture(self, folder: str | os.PathLike[str], *, format: str = "canonical",
                       name: str = "") -> dict:
        """Declare a capture by the manifest of `folder` (see `manifest_of`)."""
        body = {"name": name or Path(folder).name, "format": format,
                "manifest": {"files": manifest_of(folder, format)}}
        return self._json("POST", "/v1/captures", json=body)

    def capture(self, capture_id: str) -> dict:
        return self._json("GET", f"/v1/captures/{capture_id}")

    def missing_files(self, capture_id: str) -> list[dict]:
        """Manifest entries the server has not received (corrupt ones included)."""
        return list(self._pages(f"/v1/captures/{capture_id}/files", {"state": "missing"}))

    def upload_capture(self, capture_id: str, folder: str | os.PathLike[str], *,
                       progress: Callable[[int, int], None] | None = None,
                       retries: int = 5) -> int:
        """Upload every file the server is missing (tus 1.0.0), resuming an interrupted file
        where the server stopped; returns the bytes the files hold. `progress(done, total)`
        is called after each chunk."""
        root = Path(folder)
        todo = self.missing_files(capture_id)
        total = sum(f["size"] for f in todo)
        done = 0
        for entry in todo:
            path = root / entry["path"]
            if not path.is_file() or path.stat().st_size != entry["size"]:
                raise ValueError(f"folder: {path} is missing or is not the {entry['size']} "
                                 "bytes the manifest declares")
            before = done
            report = (lambda n, b=before: progress(b + n, total)) if progress else None
            for attempt in range(retries + 1):
                try:
                    self._upload_file(capture_id, path, entry["path"], report)
                    break
                except (httpx.TransportError, ApiError) as exc:
                    # A retryable answer or a dropped connection: HEAD says where to go on
                    # (a file that failed its SHA-256 is gone there, so it starts over).
                    if attempt == retries or not (isinstance(exc, httpx.TransportError)
                                                  or exc.retryable):
                        raise
                    time.sleep(min(0.5 * 2 ** attempt, 10.0))
            done = before + entry["size"]
        return done

    def _remember(self, capture_id: str, rel: str, url: str | None) -> None:
        key = f"{capture_id}/{rel}"
        if url is None:
            self._uploads.pop(key, None)
        else:
            self._uploads[key] = url
        if self.url_store is not None:
            self.url_store.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.url_store.with_name(self.url_store.name + ".tmp")
            tmp.write_text(json.dumps(self._uploads))
            os.replace(tmp, self.url_store)

    def _forget(self, capture_id: str, rel: str) -> None:
        self._remember(capture_id, rel, None)

    def _offset(self, url: str) -> int | None:
        """Where the upload at `url` stands; None when the server no longer knows it."""
        r = self.http.head(url, headers={"Tus-Resumable": "1.0.0"})
        if r.status_code in (404, 410):
            return None
        return int(self._check(r).headers["Upload-Offset"])

    def _upload_file(self, capture_id: str, path: Path, rel: str,
                     progress: Callable[[int], None] | None) -> None:
        tus = {"Tus-Resumable": "1.0.0"}
        size = path.stat().st_size
        url = self._uploads.get(f"{capture_id}/{rel}")
        offset = self._offset(url) if url is not None else None
        if offset is None:
            meta = ",".join(f"{k} {base64.b64encode(v.encode()).decode()}"
                            for k, v in (("capture", capture_id), ("path", rel)))
            r = self._check(self.http.post("/v1/uploads", headers={
                **tus, "Upload-Length": str(size), "Upload-Metadata": meta}))
            url, offset = r.headers["Location"], int(r.headers.get("Upload-Offset", 0))
            self._remember(capture_id, rel, url)
        with open(path, "rb") as f:
            while offset < size:
                f.seek(offset)
                if self.chunk_checksum is None:  # the rest of the file in one request
                    length, body = size - offset, _blocks(f, size - offset, offset, progress)
                    headers = {}
                else:
                    body = f.read(CHUNK)
                    length, digest = len(body), hashlib.new(self.chunk_checksum, body).digest()
                    headers = {"Upload-Checksum": f"{self.chunk_checksum} "
                                                  f"{base64.b64encode(digest).decode()}"}
                r = self.http.patch(url, content=body, headers={
                    **tus, **headers, "Upload-Offset": str(offset),
                    "Content-Length": str(length),
                    "Content-Type": "application/offset+octet-stream"})
                if r.status_code == 409 and "Upload-Offset" in r.headers:
                    r.read()  # an earlier attempt got further than we knew: go on from there
                else:
                    self._check(r)
                offset = int(r.headers["Upload-Offset"])
                if progress is not None:
                    progress(offset)
        self._forget(capture_id, rel)

    def commit(self, capture_id: str, *, poll: float = 1.0, timeout: float = 3600) -> dict:
        """Validate and freeze the capture, waiting while the server validates; raises
        ApiError when files are missing (409) or the capture is not valid (422)."""
        cap = self._json("POST", f"/v1/captures/{capture_id}/commit")
        deadline = time.monotonic() + timeout
        while cap["state"] == "committing" and time.monotonic() < deadline:
            time.sleep(poll)
            cap = self.capture(capture_id)
        if cap["state"] == "uploading" and cap.get("error"):
            e = cap["error"]
            # The server's rule (service.upload.commit.commit_status): the files decide these.
            status = 422 if e["code"] in ("invalid_capture", "import_failed") else 500
            raise ApiError(status, e["code"],
                           e["message"], e.get("retryable", False), e.get("details"))
        if cap["state"] != "ready":
            raise TimeoutError(f"capture {capture_id} is still {cap['state']} after "
                               f"{timeout:.0f} s")
        return cap

    # -- jobs ---------------------------------------------------------------------------------
    def upload_envmap(self, path: str | os.PathLike[str]) -> dict:
        """Upload an equirectangular .exr or .hdr environment map as an asset (checked by the
        server: 422 with the reason when it is not one); returns the asset."""
        path = Path(path)
        with open(path, "rb") as f:
            return self._json("POST", "/v1/assets", params={"filename": path.name,
                                                            "kind": "envmap"},
                              content=f.read(),
                              headers={"Content-Type": "application/octet-stream"})
