"""Committing a capture: every manifest file received -> validate (core.data; other formats are
imported into the canonical layout) -> freeze into the artifact store under captures/<id>/ ->
state ready with a summary. An invalid capture stays uploading with the problems recorded (each
names its file), nothing deleted, so the client can fix files and commit again.

Validation runs in a background thread; the request waits `commit_wait_seconds` for it and
otherwise answers 202 (state committing). A commit whose process died is noticed at start-up
(or by the next commit request) and the capture goes back to uploading.
"""

from __future__ import annotations

import collections
import errno
import logging
import os
import secrets
import shutil
import threading
from pathlib import Path
from typing import Any

from sqlalchemy import select, update

from core.data import CaptureError, check_capture, detect_format, import_capture
from service.deps import Services
from service.errors import ApiError
from service.upload.staging import file_states
from worker.models import Capture, Upload, utcnow
from worker.redact import SERVER, redact
from worker.store import Owner

__all__ = ["INPUT_CODES", "Committer", "begin_commit", "commit_status", "missing_files",
           "recover_commits", "run_commit"]

log = logging.getLogger("dgs.service")
OWNER_KEY = "commit_owner"
INPUT_CODES = ("invalid_capture", "import_failed")
"""Error codes of a commit that the client's files decide (answered 422, not retryable)."""
_TRANSIENT_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EROFS, errno.EMFILE,
                     errno.ENFILE, errno.ENOMEM, errno.EAGAIN, errno.EBUSY, errno.ETIMEDOUT,
                     errno.ESTALE}


def missing_files(services: Services, capture_id: str) -> list[str]:
    """Manifest paths not received, or whose staged file is gone or has the wrong size."""
    manifest = services.manifests.get(capture_id)
    states = file_states(services.store, capture_id)
    out = []
    for path, (size, _) in (manifest.files.items() if manifest else ()):
        if states.get(path) != "received":
            out.append(path)
            continue
        try:
            ok = services.staging.file(capture_id, path).stat().st_size == size
        except OSError:
            ok = False
        if not ok:  # the staged copy was lost: it has to be sent again
            out.append(path)
            with services.store.session() as s:
                s.execute(update(Upload).where(Upload.capture_id == capture_id, Upload.path == path,
                                               Upload.state == "received").values(state="corrupt"))
    return out


def _owner_dead(capture: Capture) -> bool:
    owner = Owner.parse(((capture.summary or {}).get(OWNER_KEY)) or "")
    return owner is None or owner.is_dead_here()


def _reset(services: Services, capture_id: str, message: str) -> bool:
    error = {"code": "commit_interrupted", "message": message, "retryable": True, "details": []}
    with services.store.session() as s:
        res = s.execute(update(Capture).where(Capture.id == capture_id,
                                              Capture.state == "committing")
                        .values(state="uploading", summary=None, error=error))
        return res.rowcount == 1


def begin_commit(services: Services, capture: Capture) -> bool:
    """Move an uploading capture with every file received to committing; True when this call
    did (and must start `run_commit`). ApiError 409 lists missing files."""
    if capture.state == "committing" and _owner_dead(capture):
        _reset(services, capture.id, "the process validating this capture stopped")
        capture.state = "uploading"
    if capture.state != "uploading":
        return False
    missing = missing_files(services, capture.id)
    if missing:
        raise ApiError(409, f"{len(missing)} file(s) not received yet, e.g. {missing[0]}; "
                            "upload them, then commit again", code="files_missing",
                       details=[{"path": p, "message": "not received"} for p in missing[:100]])
    with services.store.session() as s:
        res = s.execute(update(Capture).where(Capture.id == capture.id,
                                              Capture.state == "uploading")
                        .values(state="committing", error=None,
                                summary={OWNER_KEY: str(Owner.current())}))
        return res.rowcount == 1


def recover_commits(services: Services) -> list[str]:
    """At start-up: captures left committing by a process that is gone go back to uploading."""
    with services.store.session(write=False) as s:
        rows = list(s.execute(select(Capture.id, Capture.summary)
                              .where(Capture.state == "committing")))
    out = []
    for capture_id, summary in rows:
        owner = Owner.parse(((summary or {}).get(OWNER_KEY)) or "")
        if (owner is None or owner.is_dead_here()) and _reset(
                services, capture_id, "the server stopped while validating; commit again"):
            log.warning("capture %s: its commit was interrupted; back to uploading", capture_id)
            out.append(capture_id)
    return out


def _resolve_format(fmt: str, src: Path) -> str:
    if fmt != "auto":
        return fmt
    if (src / "capture.json").is_file():
        return "canonical"
    return detect_format(src)


def summarize(capture, fmt: str) -> dict[str, Any]:
    """frames, cameras, image sizes, how many views have masks and normals, the cameras the
    capture holds out (its test_cameras, or None) and what its import changed (warnings)."""
    sizes = collections.Counter((c.width, c.height) for c in capture.cameras)
    views = capture.views()
    return {"frames": len(capture.frames), "cameras": len(capture.cameras),
            "camera_ids": [c.id for c in capture.cameras], "views": len(views),
            "image_sizes": [{"width": w, "height": h, "cameras": n}
                            for (w, h), n in sorted(sizes.items())],
            "masks": sum(v.mask is not None for v in views),
            "normals": sum(v.normal is not None for v in views), "source_format": fmt,
            "test_cameras": None if capture.test_cameras is None else list(capture.test_cameras),
            "import_warnings": _import_warnings(capture.import_record)}


def _import_warnings(record: Any) -> list[str]:
    """The import record's warnings; a canonical capture.json's "import" is the client's JSON,
    so anything but a list of strings there is no warning of ours."""
    found = record.get("warnings") if isinstance(record, dict) else None
    return [w for w in found if isinstance(w, str)] if isinstance(found, list) else []


def freeze(services: Services, root: Path, capture_id: str) -> None:
    """Move the validated tree into the artifact store (a rename when the local store is on
    the same file system; else a copy of every file)."""
    prefix = f"captures/{capture_id}"
    services.blobs.delete_prefix(prefix)  # what an interrupted earlier attempt left
    dest = services.blobs.local_path(prefix)
    if dest is not None:
        dest.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.rename(root, dest)
            return
        except OSError:
            pass  # another file system: copy below
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        services.blobs.put_file(f"{prefix}/{path.relative_to(root).as_posix()}", path)


def commit_status(error: dict[str, Any]) -> int:
    """The HTTP status of a failed commit's recorded error: 422 when the client's files decide
    the outcome (`INPUT_CODES`: the same files always fail the same way, so nothing invites a
    retry, which clients do for every 5xx), 500 when the server's disk or store failed."""
    return 422 if error.get("code") in INPUT_CODES else 500


def _validated(src: Path, out: Path, fmt: str, limit: int):
    """(capture, its root) of the received files: checked in place (canonical) or imported
    into `out`."""
    if fmt == "canonical":
        return check_capture(src, max_pixels=limit), src
    shutil.rmtree(out, ignore_errors=True)
    return import_capture(src, out, fmt, link=True, max_pixels=limit), out


def _input_error(exc: CaptureError, roots: list) -> dict[str, Any]:
    details = [{"path": redact(p.path, roots), "message": redact(p.message, roots)}
               for p in exc.problems]
    first = f"{details[0]['path']}: {details[0]['message']}" if details else "invalid"
    more = f" (and {len(details) - 1} more)" if len(details) > 1 else ""
    return {"code": "invalid_capture", "retryable": False,
            "message": f"not a valid capture: {first}{more}", "details": details[:1000]}


def _bug(capture_id: str, fmt: str, exc: Exception, roots: list) -> dict[str, Any]:
    """An importer or the validation raised something else than CaptureError on the client's
    files: a bug, logged with its traceback under a reference; answered 422 `import_failed`
    (not retryable: the same files fail the same way), never 500 retryable (docs/decisions/
    2026-11-29-importers-fail-closed.md)."""
    ref = secrets.token_hex(4)
    log.error("capture %s: the %s importer failed on the client's files (ref %s)", capture_id,
              fmt, ref, exc_info=exc)
    what = redact(f"{type(exc).__name__}: {exc}", roots)[:300]
    step = "validation" if fmt == "canonical" else f"the {fmt} importer"
    return {"code": "import_failed", "retryable": False, "details": [],
            "message": f"{step} failed on these files ({what}); this is a bug in "
                       f"the server, logged as {ref}. Committing the same files again gives "
                       "the same answer: change them, or report the bug with the reference"}


def run_commit(services: Services, capture_id: str) -> None:
    """Validate and freeze a committing capture; records the outcome (never raises)."""
    src = services.staging.files_dir(capture_id)
    out = services.staging.capture_dir(capture_id) / "canonical"
    with services.store.session(write=False) as s:
        fmt = s.scalar(select(Capture.format).where(Capture.id == capture_id))
    # Problems name the client's files (manifest paths), whether they are in the received
    # folder or the imported copy; nothing else of the server.
    roots = [(src, ""), (out, ""), (services.settings.data_dir, SERVER),
             (services.settings.scratch, SERVER)]
    try:
        fmt = _resolve_format(fmt, src)
        capture, root = _validated(src, out, fmt, services.settings.max_image_pixels)
        summary = summarize(capture, fmt)
    except CaptureError as exc:
        _fail(services, capture_id, _input_error(exc, roots))
        return
    except Exception as exc:
        if not _transient(exc):
            _fail(services, capture_id, _bug(capture_id, fmt, exc, roots))
            return
        log.exception("capture %s: commit failed", capture_id)
        _fail(services, capture_id, _internal(exc, roots))
        return
    try:
        freeze(services, root, capture_id)
    except Exception as exc:  # disk full, store unreachable: the client may commit again
        log.exception("capture %s: commit failed", capture_id)
        _fail(services, capture_id, _internal(exc, roots))
        return
    with services.store.session() as s:
        s.execute(update(Capture).where(Capture.id == capture_id).values(
            state="ready", summary=summary, error=None, committed_at=utcnow()))
        s.execute(update(Upload).where(Upload.capture_id == capture_id,
                                       Upload.state == "receiving").values(state="terminated"))
    services.staging.remove(capture_id)
    services.manifests.forget(capture_id)


def _transient(exc: Exception) -> bool:
    """Whether `exc` is the server's trouble (a full or failing disk, memory), which may pass,
    rather than something the client's files caused."""
    return isinstance(exc, MemoryError) or (
        isinstance(exc, OSError) and exc.errno in _TRANSIENT_ERRNOS)


def _internal(exc: Exception, roots: list) -> dict[str, Any]:
    return {"code": "internal", "retryable": True, "details": [],
            "message": redact(f"commit failed: {type(exc).__name__}: {exc}", roots)}


def _fail(services: Services, capture_id: str, error: dict[str, Any]) -> None:
    with services.store.session() as s:
        s.execute(update(Capture).where(Capture.id == capture_id).values(
            state="uploading", summary=None, error=error))


class Committer:
    """Background commit threads of this process, by capture id."""

    def __init__(self, services: Services):
        self.services = services
        self._running: dict[str, threading.Event] = {}
        self._lock = threading.Lock()

    def start(self, capture_id: str) -> threading.Event:
        with self._lock:
            done = self._running.get(capture_id)
            if done is not None:
                return done
            done = self._running[capture_id] = threading.Event()

        def work() -> None:
            try:
                run_commit(self.services, capture_id)
            finally:
                with self._lock:
                    self._running.pop(capture_id, None)
                done.set()

        threading.Thread(target=work, name=f"commit-{capture_id}", daemon=True).start()
        return done

    def running(self, capture_id: str) -> threading.Event | None:
        with self._lock:
            return self._running.get(capture_id)
