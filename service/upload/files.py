"""What a tus upload does to the job store and the staging folder (blocking; the uploads router
calls these in worker threads): create, record progress, complete against the manifest,
terminate."""

from __future__ import annotations

import hashlib
import logging
import os

from sqlalchemy import select, update

from service.deps import Services
from service.errors import ApiError
from service.lookups import get_capture, missing
from service.upload.manifest import check_path
from worker.models import Upload
from worker.store import new_id

__all__ = ["complete_upload", "create_upload", "record_offset", "terminate_upload"]

log = logging.getLogger("dgs.service")


def require_uploading(services: Services, capture_id: str, tenant: str) -> None:
    capture = get_capture(services.store, capture_id, tenant)
    if capture.state != "uploading":
        raise ApiError(409, f"capture {capture_id} is {capture.state}; files can only be "
                            "uploaded while it is uploading")


def create_upload(services: Services, tenant: str, capture_id: str, path: str,
                  length: int) -> Upload:
    """A new upload of manifest file `path` (its declared size must be `length`)."""
    settings = services.settings
    if length > settings.max_file_bytes:
        raise ApiError(413, f"Upload-Length {length} exceeds the limit per file "
                            f"({settings.max_file_bytes} bytes)")
    check_path(path, "Upload-Metadata path", settings.max_path_bytes)
    require_uploading(services, capture_id, tenant)
    entry = services.manifests.get(capture_id)
    if entry is None:
        raise missing("capture", capture_id)
    if path not in entry.files:
        raise ApiError(422, f"{path!r} is not in capture {capture_id}'s manifest",
                       details=[{"path": path, "message": "not in the manifest"}])
    size = entry.files[path][0]
    if size != length:
        raise ApiError(422, f"{path}: Upload-Length is {length} but the manifest declares "
                            f"{size} bytes", details=[{"path": path, "message": "wrong length"}])
    upload = Upload(id=new_id("upl"), tenant=tenant, capture_id=capture_id, path=path,
                    length=length, offset=0, state="receiving")
    services.staging.parts_dir(capture_id).mkdir(parents=True, exist_ok=True)
    services.staging.part(capture_id, upload.id).touch()
    with services.store.session() as s:
        s.add(upload)
    if length == 0:
        complete_upload(services, upload, hashlib.sha256().hexdigest())
    return upload


def record_offset(services: Services, upload_id: str, offset: int) -> None:
    with services.store.session() as s:
        s.execute(update(Upload).where(Upload.id == upload_id, Upload.state == "receiving")
                  .values(offset=offset))


def complete_upload(services: Services, upload: Upload, sha256: str) -> str:
    """The last byte arrived: compare with the manifest, then move the part into the capture
    (received), or drop it when the path was already received (duplicate: re-sending a file is
    a no-op), or drop it and answer 460 (corrupt)."""
    capture_id, staging = upload.capture_id, services.staging
    part = staging.part(capture_id, upload.id)
    entry = services.manifests.get(capture_id)
    expected = entry.files[upload.path][1] if entry is not None else None
    services.hashes.drop(upload.id)
    if sha256 != expected:
        part.unlink(missing_ok=True)
        _set_state(services, upload.id, "corrupt", upload.length)
        raise ApiError(460, f"{upload.path}: the received bytes have SHA-256 {sha256}, the "
                            f"manifest says {expected}; nothing was kept. Upload the file "
                            "again (a new POST)", code="checksum_mismatch", retryable=True,
                       details=[{"path": upload.path, "message": "sha256 does not match"}])
    with services.store.session() as s:
        done = s.scalar(select(Upload.id).where(
            Upload.capture_id == capture_id, Upload.path == upload.path,
            Upload.state == "received", Upload.id != upload.id).limit(1))
        row = s.get(Upload, upload.id)
        if done is not None:
            part.unlink(missing_ok=True)
            state = "duplicate"
        else:
            dest = staging.file(capture_id, upload.path)
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(part, dest)
            state = "received"
        row.state, row.offset = state, upload.length
    staging.lock(capture_id, upload.id).unlink(missing_ok=True)
    return state


def _set_state(services: Services, upload_id: str, state: str, offset: int | None = None) -> None:
    values: dict = {"state": state}
    if offset is not None:
        values["offset"] = offset
    with services.store.session() as s:
        s.execute(update(Upload).where(Upload.id == upload_id).values(**values))


def terminate_upload(services: Services, upload: Upload) -> None:
    """tus termination: the part is removed and the upload forgotten (404 from now on). A
    received file belongs to its capture and stays."""
    if upload.state == "received":
        raise ApiError(409, f"upload {upload.id} is complete: {upload.path} is part of "
                            f"capture {upload.capture_id} and stays")
    services.staging.part(upload.capture_id, upload.id).unlink(missing_ok=True)
    services.staging.lock(upload.capture_id, upload.id).unlink(missing_ok=True)
    services.hashes.drop(upload.id)
    _set_state(services, upload.id, "terminated")
