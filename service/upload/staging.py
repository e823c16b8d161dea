"""Where a capture's files wait until it is committed, and what the API knows about them.

    <data_dir>/uploads/<capture>/parts/<upload>.part   a tus upload being received
    <data_dir>/uploads/<capture>/parts/<upload>.lock   its lock (one writer at a time)
    <data_dir>/uploads/<capture>/files/<path>          received files, verified against the manifest
    <data_dir>/uploads/.tmp/                           archive and asset bodies being spooled

Every API process that takes uploads must see the same data_dir (one machine, or a shared
volume). A manifest path is split on '/' and joined under files/ only after
`service.upload.manifest.check_path` accepted it.
"""

from __future__ import annotations

import shutil
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import select

from worker.models import Capture, Upload
from worker.store import JobStore

__all__ = ["Manifest", "ManifestCache", "Staging", "file_states"]


class Staging:
    def __init__(self, root: Path):
        self.root = root

    def capture_dir(self, capture_id: str) -> Path:
        return self.root / capture_id

    def files_dir(self, capture_id: str) -> Path:
        return self.capture_dir(capture_id) / "files"

    def parts_dir(self, capture_id: str) -> Path:
        return self.capture_dir(capture_id) / "parts"

    def part(self, capture_id: str, upload_id: str) -> Path:
        return self.parts_dir(capture_id) / f"{upload_id}.part"

    def lock(self, capture_id: str, upload_id: str) -> Path:
        return self.parts_dir(capture_id) / f"{upload_id}.lock"

    def file(self, capture_id: str, path: str) -> Path:
        return self.files_dir(capture_id).joinpath(*path.split("/"))

    def tmp_dir(self) -> Path:
        path = self.root / ".tmp"
        path.mkdir(parents=True, exist_ok=True)
        return path

    def remove(self, capture_id: str) -> None:
        shutil.rmtree(self.capture_dir(capture_id), ignore_errors=True)


@dataclass(frozen=True)
class Manifest:
    files: dict[str, tuple[int, str]]
    """path -> (size, sha256), in manifest order."""
    version: object = None
    """The capture's updated_at when this was read (a changed row is read again)."""


class ManifestCache:
    """Manifests by capture id. A large one (a million files) costs seconds to parse, so the
    few most recent stay in memory; the row's updated_at tells when one was amended (by any
    process) and must be read again."""

    def __init__(self, store: JobStore, size: int = 8):
        self.store, self.size = store, size
        self._items: OrderedDict[str, Manifest] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, capture_id: str) -> Manifest | None:
        with self.store.session(write=False) as s:
            version = s.scalar(select(Capture.updated_at).where(Capture.id == capture_id))
            if version is None:
                return None
            with self._lock:
                cached = self._items.get(capture_id)
                if cached is not None and cached.version == version:
                    self._items.move_to_end(capture_id)
                    return cached
            raw = s.scalar(select(Capture.manifest).where(Capture.id == capture_id))
        manifest = Manifest({f["path"]: (int(f["size"]), f["sha256"]) for f in raw or []},
                            version)
        self.put(capture_id, manifest)
        return manifest

    def put(self, capture_id: str, manifest: Manifest) -> None:
        with self._lock:
            self._items[capture_id] = manifest
            self._items.move_to_end(capture_id)
            while len(self._items) > self.size:
                self._items.popitem(last=False)

    def forget(self, capture_id: str) -> None:
        with self._lock:
            self._items.pop(capture_id, None)


def file_states(store: JobStore, capture_id: str) -> dict[str, str]:
    """path -> "received" or "corrupt" (its last upload did not match the manifest) for every
    file that is not simply missing."""
    out: dict[str, str] = {}
    with store.session(write=False) as s:
        rows = s.execute(select(Upload.path, Upload.state).where(
            Upload.capture_id == capture_id, Upload.state.in_(("received", "corrupt"))))
        for path, state in rows:
            if out.get(path) != "received":
                out[path] = state
    return out
