"""A small Python client of the HTTP API (docs/design.md 3.5): what a studio's script does with the
service. Torch-free; only httpx.

    c = Client("http://127.0.0.1:8000", api_key)
    cap = c.create_capture("capture/")             # manifest: path, size, sha256 per file
    c.upload_capture(cap["id"], "capture/")        # tus, resumable, missing files only
    c.commit(cap["id"])
    job = c.submit(cap["id"], {"preset": "fast"})
    job = c.wait(job["id"], on_event=print)        # server-sent events, reconnecting
    c.download_all(job["id"], "results/")          # Range-resumed, SHA-256 checked
    env = c.upload_envmap("studio.exr")            # an environment map asset
    render = c.render(job["id"], env["id"], orbit=24)
    render = c.wait(render["id"])                  # a relight job, followed the same way
    c.download_all(render["id"], "relit/", kind="video")
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal
from urllib.parse import quote

import httpx

from core.files import sha256_file

__all__ = ["ApiError", "Client", "Event", "manifest_of"]

CHUNK = 8 << 20
"""Bytes per tus PATCH when each carries a checksum (Client chunk_checksum)."""
TERMINAL = ("succeeded", "failed", "cancelled")
CANONICAL = ("capture.json", "images/", "masks/", "normals/")
"""What a canonical capture holds (docs/design.md 3.1); anything else in its folder (a synthetic
capture's ground truth, notes) stays on the client."""


class ApiError(RuntimeError):
    """An error answer of the API: status, code, message, retryable, details."""

    def __init__(self, status: int, code: str, message: str, retryable: bool = False,
                 details: list[dict] | None = None):
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message = status, code, message
        self.retryable, self.details = retryable, details or []


@dataclass(frozen=True)
class Event:
    """One server-sent event of a job: its id, kind (state, progress, artifact) and data."""

    id: int
    kind: str
    data: dict[str, Any]


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


class Client:
    """The API at `base_url`, with a bearer key (None when the server has no keys).

    `url_store`: a JSON file where the URLs of begun uploads are kept, so that another
    process (after a crash, a closed laptop) resumes them instead of starting over.
    `chunk_checksum`: None (default) streams each file in one PATCH; a dropped connection
    loses nothing (the server keeps what arrived, HEAD says where to go on) and the server
    checks the whole file against the manifest's SHA-256. "sha1" (or sha256, md5) sends
    CHUNK-byte PATCHes with a tus Upload-Checksum each, so a chunk damaged on the way is
    refused alone and sent again; it costs a hash on both sides and a request per chunk
    (benchmarks/service.py measures both)."""

    def __init__(self, base_url: str, api_key: str | None = None, *, timeout: float = 60.0,
                 transport: httpx.BaseTransport | None = None,
                 url_store: str | os.PathLike[str] | None = None,
                 chunk_checksum: Literal["sha1", "sha256", "md5"] | None = None):
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.http = httpx.Client(base_url=base_url.rstrip("/"), headers=headers,
                                 timeout=timeout, transport=transport)
        self.url_store = Path(url_store) if url_store is not None else None
        self.chunk_checksum = chunk_checksum
        self._uploads: dict[str, str] = (
            json.loads(self.url_store.read_text()) if self.url_store is not None
            and self.url_store.is_file() else {})
        """Upload URLs by "capture/path": resumed instead of started over."""

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- plumbing -----------------------------------------------------------------------------
    @staticmethod
    def _check(r: httpx.Response) -> httpx.Response:
        if r.status_code < 400:
            return r
        try:
            err = r.json()["error"]
        except (ValueError, KeyError, TypeError):
            err = {"code": "http_error", "message": r.text[:500]}
        raise ApiError(r.status_code, err.get("code", "?"), err.get("message", ""),
                       bool(err.get("retryable")), err.get("details"))

    def _json(self, method: str, url: str, **kw) -> Any:
        r = self._check(self.http.request(method, url, **kw))
        return r.json() if r.content else None

    def _pages(self, url: str, params: dict) -> Iterator[dict]:
        cursor = None
        while True:
            page = self._json("GET", url, params={**params, **({"cursor": cursor}
                                                               if cursor else {})})
            yield from page["items"]
            cursor = page.get("next_cursor")
            if not cursor:
                return

    def info(self) -> dict:
        return self._json("GET", "/v1/info")

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
            raise ApiError(422 if e["code"] == "invalid_capture" else 500, e["code"],
                           e["message"], e.get("retryable", False), e.get("details"))
        if cap["state"] != "ready":
            raise TimeoutError(f"capture {capture_id} is still {cap['state']} after "
                               f"{timeout:.0f} s")
        return cap

    # -- jobs ---------------------------------------------------------------------------------
    def submit(self, capture_id: str, params: dict | None = None, *,
               pipeline: str = "reconstruct", name: str = "") -> dict:
        """Queue a job (202); returns it (state queued)."""
        return self._json("POST", "/v1/jobs", json={
            "capture_id": capture_id, "pipeline": pipeline, "params": params or {},
            "name": name})

    def job(self, job_id: str) -> dict:
        return self._json("GET", f"/v1/jobs/{job_id}")

    def cancel(self, job_id: str) -> dict:
        return self._json("POST", f"/v1/jobs/{job_id}/cancel")

    def logs(self, job_id: str) -> list[str]:
        lines, offset = [], 0
        while True:
            page = self._json("GET", f"/v1/jobs/{job_id}/logs", params={"offset": offset})
            lines += page["lines"]
            if page["next_offset"] == offset or not page["lines"]:
                return lines
            offset = page["next_offset"]

    def events(self, job_id: str, last_event_id: int | None = None) -> Iterator[Event]:
        """The job's server-sent events on one connection, after `last_event_id` when given
        (else from its current state), until the server ends the stream."""
        headers = {"Accept": "text/event-stream"}
        if last_event_id is not None:
            headers["Last-Event-ID"] = str(last_event_id)
        with self.http.stream("GET", f"/v1/jobs/{job_id}/events", headers=headers,
                              timeout=httpx.Timeout(60.0, read=120.0)) as r:
            if r.status_code >= 400:
                r.read()
                self._check(r)
            fields: dict[str, str] = {}
            for line in r.iter_lines():
                if line:
                    if not line.startswith(":"):
                        key, _, value = line.partition(":")
                        fields[key] = value[1:] if value.startswith(" ") else value
                    continue
                if "data" in fields:
                    yield Event(int(fields.get("id") or 0), fields.get("event", "message"),
                                json.loads(fields["data"]))
                fields = {}

    def wait(self, job_id: str, on_event: Callable[[Event], None] | None = None, *,
             timeout: float | None = None) -> dict:
        """Follow the job's events until it ends, reconnecting with Last-Event-ID when the
        connection drops (no event is seen twice); returns the job."""
        last = None
        deadline = None if timeout is None else time.monotonic() + timeout
        failures = 0
        while deadline is None or time.monotonic() < deadline:
            try:
                for event in self.events(job_id, last):
                    failures = 0
                    last = event.id if event.id else last
                    if on_event is not None:
                        on_event(event)
                    if event.kind == "state" and event.data.get("state") in TERMINAL:
                        return self.job(job_id)
            except httpx.TransportError:
                # Reconnect (after the last event seen) so the events missed meanwhile,
                # the final state included, still reach `on_event`.
                time.sleep(min(0.1 * 2 ** failures, 5.0))
                failures += 1
                continue
            job = self.job(job_id)
            if job["state"] in TERMINAL:
                return job
            time.sleep(1.0)
        raise TimeoutError(f"job {job_id} did not end within {timeout:.0f} s")

    # -- relighting ---------------------------------------------------------------------------
    def upload_envmap(self, path: str | os.PathLike[str]) -> dict:
        """Upload an equirectangular .exr or .hdr environment map as an asset (checked by the
        server: 422 with the reason when it is not one); returns the asset."""
        path = Path(path)
        with open(path, "rb") as f:
            return self._json("POST", "/v1/assets", params={"filename": path.name,
                                                            "kind": "envmap"},
                              content=f.read(),
                              headers={"Content-Type": "application/octet-stream"})

    def render(self, job_id: str, envmap: str, *, lights: list[dict] | None = None,
               name: str = "", **params: Any) -> dict:
        """Request relit renders of the succeeded reconstruction `job_id` under envmap asset
        `envmap` (202); returns the render job (pipeline relight), to follow with `wait` and
        download like any job (artifacts of kind relit, video, relight). `lights`:
        [{"kind": "directional", "direction": [x, y, z], "intensity": i, "color": [r, g, b]}
        or {"kind": "point", "position": [...], ...}]; `params`: rotation_deg, exposure,
        cameras, frames, orbit, fps, ao, capture_light (GET /v1/pipelines has them all)."""
        body = {"job_id": job_id, "envmap": envmap, "lights": lights or [], "name": name,
                **params}
        return self._json("POST", "/v1/renders", json=body)

    def export(self, job_id: str, formats: tuple[str, ...] = ("stream",), *, name: str = "",
               **params: Any) -> dict:
        """Request an export of the succeeded reconstruction `job_id` (202): the relightable
        stream (export/stream.dgss, kind stream), SPZ or PLY per frame; returns the export job
        (pipeline export), to follow with `wait`. `params`: frames, fps, position_tolerance."""
        return self._json("POST", "/v1/exports", json={"job_id": job_id, "formats": list(formats),
                                                        "name": name, **params})

    # -- artifacts ----------------------------------------------------------------------------
    def artifacts(self, job_id: str, kind: str | None = None) -> list[dict]:
        return list(self._pages(f"/v1/jobs/{job_id}/artifacts", {"kind": kind} if kind else {}))

    def download(self, job_id: str, path: str, dest: str | os.PathLike[str], *,
                 sha256: str | None = None) -> Path:
        """Download one artifact to `dest`. Bytes of an interrupted download (dest + ".part")
        are kept and the rest fetched with Range (If-Range: the artifact's ETag, so a changed
        artifact starts over); with `sha256` the result is checked and a finished `dest` that
        matches is not fetched again."""
        dest = Path(dest)
        if sha256 is not None and dest.is_file() and sha256_file(dest) == sha256:
            return dest
        dest.parent.mkdir(parents=True, exist_ok=True)
        part = dest.with_name(dest.name + ".part")
        have = part.stat().st_size if part.exists() else 0
        headers = {}
        if have:
            headers["Range"] = f"bytes={have}-"
            if sha256 is not None:
                headers["If-Range"] = f'"{sha256}"'
        with self.http.stream("GET", f"/v1/jobs/{job_id}/artifacts/{quote(path)}",
                              headers=headers) as r:
            if r.status_code == 416 and have:  # the part already holds every byte
                r.read()
            else:
                if r.status_code >= 400:
                    r.read()
                    self._check(r)
                with open(part, "ab" if r.status_code == 206 else "wb") as f:
                    for chunk in r.iter_bytes(1 << 20):
                        f.write(chunk)
        if sha256 is not None and sha256_file(part) != sha256:
            part.unlink()
            raise ApiError(502, "checksum_mismatch", f"{path}: the downloaded bytes do not "
                           "have the artifact's SHA-256; download it again", True)
        os.replace(part, dest)
        return dest

    def download_all(self, job_id: str, folder: str | os.PathLike[str],
                     kind: str | None = None,
                     progress: Callable[[int, int], None] | None = None) -> list[Path]:
        """Every artifact (of `kind`) into `folder`, keeping the run directory's layout;
        each checked against its SHA-256. `progress(files done, files)`."""
        folder = Path(folder).resolve()
        items = self.artifacts(job_id, kind)
        out = []
        for i, a in enumerate(items):
            dest = (folder / a["path"]).resolve()
            if not dest.is_relative_to(folder):  # never written outside `folder`
                raise ApiError(502, "invalid_path", f"artifact path {a['path']!r} leaves "
                               f"{folder}")
            out.append(self.download(job_id, a["path"], dest, sha256=a["sha256"]))
            if progress is not None:
                progress(i + 1, len(items))
        return out

