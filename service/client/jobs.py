"""Jobs through the API: submit, follow (server-sent events, reconnecting), cancel; renders and
exports of a finished reconstruction; artifacts downloaded with Range and checked."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx

from core.files import sha256_file
from service.client.http import TERMINAL, ApiError, Event, Http

__all__ = ["Jobs"]


class Jobs(Http):
    """Jobs, their events and artifacts."""

    def submit(self, capture_id: str, params: dict | None = None, *,
               pipeline: str | None = None, name: str = "",
               idempotency_key: str | None = None) -> dict:
        """Queue a job (202); returns it (state queued). `pipeline`: one of GET /v1/pipelines
        that runs on a capture (None: the server's default, a reconstruction). Sent again on
        a lost connection, a timeout, a 5xx or a 429 (after its Retry-After) with one
        Idempotency-Key (`idempotency_key`, else a new UUID), so it makes one job; give your
        own key to make a submit safe across processes too."""
        body = {"capture_id": capture_id, "params": params or {}, "name": name}
        if pipeline is not None:
            body["pipeline"] = pipeline
        return self._submit("/v1/jobs", body, idempotency_key)

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
        connection drops (no event is seen twice); returns the job. While the server refuses
        another stream (429: the tenant's cap), the job is polled instead."""
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
                self.sleep(min(0.1 * 2 ** failures, 5.0))
                failures += 1
                continue
            except ApiError as exc:  # too many streams open: poll, and reconnect when one
                if exc.status != 429:  # may have been freed (Retry-After)
                    raise
                self.sleep(min(exc.retry_after or 1.0, self.max_wait))
            job = self.job(job_id)
            if job["state"] in TERMINAL:
                return job
            self.sleep(1.0)
        raise TimeoutError(f"job {job_id} did not end within {timeout:.0f} s")

    # -- relighting ---------------------------------------------------------------------------
    def render(self, job_id: str, envmap: str, *, lights: list[dict] | None = None,
               name: str = "", idempotency_key: str | None = None, **params: Any) -> dict:
        """Request relit renders of the succeeded reconstruction `job_id` under envmap asset
        `envmap` (202); returns the render job (pipeline relight), to follow with `wait` and
        download like any job (artifacts of kind relit, video, relight). `lights`:
        [{"kind": "directional", "direction": [x, y, z], "intensity": i, "color": [r, g, b]}
        or {"kind": "point", "position": [...], ...}]; `params`: rotation_deg, exposure,
        cameras, frames, orbit, fps, ao, capture_light (GET /v1/pipelines has them all).
        Sent again safely as `submit` is."""
        body = {"job_id": job_id, "envmap": envmap, "lights": lights or [], "name": name,
                **params}
        return self._submit("/v1/renders", body, idempotency_key)

    def export(self, job_id: str, formats: tuple[str, ...] = ("stream",), *, name: str = "",
               idempotency_key: str | None = None, **params: Any) -> dict:
        """Request an export of the succeeded reconstruction `job_id` (202): the relightable
        stream (export/stream.dgss, kind stream), SPZ or PLY per frame; returns the export job
        (pipeline export), to follow with `wait`. `params`: frames, fps, position_tolerance.
        Sent again safely as `submit` is."""
        return self._submit("/v1/exports", {"job_id": job_id, "formats": list(formats),
                                            "name": name, **params}, idempotency_key)

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
