"""/v1/captures: declare a capture's files (manifest), follow which arrived, commit it (validate
and freeze), delete it; or upload a small one as a single zip (/v1/captures/archive)."""

from __future__ import annotations

import secrets
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import JSONResponse
from pydantic import AwareDatetime
from starlette.concurrency import run_in_threadpool as run

from service.auth import TenantDep
from service.body import JsonRoute, body_limit
from service.deps import Services, ServicesDep, default_expiry, location
from service.errors import COMMON, ApiError, ErrorInfo, error_responses
from service.lookups import deleted, get_capture
from service.pagination import after, decode_cursor, encode_cursor, next_cursor
from service.schemas import (
    CaptureFilesOut,
    CaptureIn,
    CaptureItem,
    CaptureOut,
    CapturePage,
    CaptureSummary,
    FileOut,
    FilePage,
    Format,
    PATCH_FILES,
    ManifestPatchIn,
    Name,
    manifest_entries,
)
from service.upload.archive import extract, inspect_zip, spool
from service.upload.commit import OWNER_KEY, begin_commit, commit_status, run_commit
from service.upload.manifest import check_manifest
from service.upload.staging import Manifest, file_states
from worker.models import Capture
from worker.store import Owner, new_id

__all__ = ["router"]

router = APIRouter(prefix="/v1/captures", tags=["captures"], route_class=JsonRoute,
                   responses=error_responses(*COMMON))
FIRST_PATHS = 20


def _links(capture_id: str) -> dict[str, str]:
    base = f"/v1/captures/{capture_id}"
    return {"self": base, "files": f"{base}/files", "commit": f"{base}/commit",
            "uploads": "/v1/uploads"}


def _item(c: Capture) -> CaptureItem:
    summary = CaptureSummary(**c.summary) if c.state == "ready" and c.summary else None
    return CaptureItem(id=c.id, name=c.name, format=c.format, state=c.state,
                       total_bytes=c.total_bytes, summary=summary, created_at=c.created_at,
                       committed_at=c.committed_at, expires_at=c.expires_at, links=_links(c.id))


def _files(services: Services, c: Capture, manifest: Manifest) -> CaptureFilesOut:
    if c.state == "ready":
        states = dict.fromkeys(manifest.files, "received")
    else:
        states = file_states(services.store, c.id)
    missing, corrupt, received_bytes = [], [], 0
    for path, (size, _) in manifest.files.items():
        state = states.get(path)
        if state == "received":
            received_bytes += size
            continue
        missing.append(path)
        if state == "corrupt":
            corrupt.append(path)
    return CaptureFilesOut(
        declared=len(manifest.files), declared_bytes=c.total_bytes,
        received=len(manifest.files) - len(missing), received_bytes=received_bytes,
        missing=len(missing), missing_paths=missing[:FIRST_PATHS], corrupt=len(corrupt),
        corrupt_paths=corrupt[:FIRST_PATHS])


def capture_out(services: Services, c: Capture) -> CaptureOut:
    manifest = services.manifests.get(c.id) or Manifest({})
    error = ErrorInfo(**c.error) if c.error and c.state == "uploading" else None
    return CaptureOut(**_item(c).model_dump(), files=_files(services, c, manifest), error=error)


def _created(request: Request, services: Services, out: CaptureOut) -> JSONResponse:
    return JSONResponse(out.model_dump(mode="json"), status_code=201, headers={
        "Location": location(services, out.links["self"])})


@router.post("", status_code=201, response_model=CaptureOut, responses=error_responses(400, 413))
@body_limit("max_manifest_bytes", lambda s: 8 * s.max_capture_files + 1024)
def create_capture(body: CaptureIn, request: Request, services: ServicesDep,
                   tenant: TenantDep) -> JSONResponse:
    """Declare a capture by its manifest; then upload each file with tus and commit."""
    files = body.manifest.files
    total = check_manifest(((f.path, f.size) for f in files), body.format, services.settings)
    manifest = manifest_entries(files)
    row = Capture(id=new_id("cap"), tenant=tenant, name=body.name, format=body.format,
                  state="uploading", manifest=manifest, total_bytes=total,
                  expires_at=default_expiry(services, body.expires_at))
    services.store.add_capture(row)
    services.manifests.put(row.id, Manifest({f["path"]: (f["size"], f["sha256"])
                                             for f in manifest}, row.updated_at))
    return _created(request, services, capture_out(services, row))


@router.get("", response_model=CapturePage)
def list_captures(services: ServicesDep, tenant: TenantDep,
                  state: Literal["uploading", "committing", "ready"] | None = None,
                  cursor: Annotated[str | None, Query(max_length=512)] = None,
                  limit: Annotated[int, Query(ge=1, le=200)] = 50) -> CapturePage:
    """The caller's captures, newest first."""
    rows, last = services.store.capture_page(tenant, state, after(cursor), limit)
    return CapturePage(items=[_item(c) for c in rows], next_cursor=next_cursor(last))


@router.get("/{capture_id}", response_model=CaptureOut)
def read_capture(capture_id: str, services: ServicesDep, tenant: TenantDep) -> CaptureOut:
    """State, received / missing / corrupt files, and the summary once ready."""
    return capture_out(services, get_capture(services.store, capture_id, tenant))


@router.get("/{capture_id}/files", response_model=FilePage)
def list_files(capture_id: str, services: ServicesDep, tenant: TenantDep,
               state: Literal["missing", "received", "corrupt"] | None = None,
               cursor: Annotated[str | None, Query(max_length=512)] = None,
               limit: Annotated[int, Query(ge=1, le=10_000)] = 1000) -> FilePage:
    """The manifest's files with their state, in manifest order; `missing` means not received
    (corrupt ones included)."""
    c = get_capture(services.store, capture_id, tenant)
    manifest = services.manifests.get(c.id) or Manifest({})
    states = (dict.fromkeys(manifest.files, "received") if c.state == "ready"
              else file_states(services.store, c.id))
    start = decode_cursor(cursor, (int,))[0] if cursor else 0
    items, index = [], start
    paths = list(manifest.files)
    while index < len(paths) and len(items) < limit:
        path = paths[index]
        index += 1
        fstate = states.get(path, "missing")
        if state is None or fstate == state or (state == "missing" and fstate == "corrupt"):
            size, digest = manifest.files[path]
            items.append(FileOut(path=path, size=size, sha256=digest, state=fstate))
    return FilePage(items=items, next_cursor=encode_cursor(index) if index < len(paths) else None)


@router.patch("/{capture_id}/manifest", response_model=CaptureOut,
              responses=error_responses(400, 409, 413))
@body_limit("max_manifest_bytes", lambda s: 8 * 2 * PATCH_FILES + 1024)
def amend_manifest(capture_id: str, body: ManifestPatchIn, services: ServicesDep,
                   tenant: TenantDep) -> CaptureOut:
    """Add, replace or remove manifest entries while uploading (to fix what a failed commit
    reported without uploading the rest again). A replaced or removed file's received copy is
    dropped."""
    changed: set[str] = set()

    def edit(c: Capture) -> set[str]:
        if c.state != "uploading":
            raise ApiError(409, f"capture {capture_id} is {c.state}; its manifest is frozen")
        files = {f["path"]: f for f in c.manifest}
        unknown = [p for p in body.remove if p not in files]
        if unknown:
            raise ApiError(422, f"remove: {unknown[0]!r} is not in the manifest",
                           details=[{"path": p, "message": "not in the manifest"}
                                    for p in unknown[:100]])
        changed.update(body.remove)
        for path in body.remove:
            del files[path]
        for f in manifest_entries(body.files):
            old = files.get(f["path"])
            if old is not None and (old["size"], old["sha256"]) != (f["size"], f["sha256"]):
                changed.add(f["path"])
            files[f["path"]] = f
        c.total_bytes = check_manifest(((p, f["size"]) for p, f in files.items()), c.format,
                                       services.settings)
        c.manifest = list(files.values())
        return changed

    c, stale = services.store.amend_manifest(capture_id, tenant, edit)
    if c is None:
        raise ApiError(404, f"no capture {capture_id!r}")
    for path in changed:
        services.staging.file(capture_id, path).unlink(missing_ok=True)
    for upload_id in stale:
        services.staging.part(capture_id, upload_id).unlink(missing_ok=True)
    return capture_out(services, get_capture(services.store, capture_id, tenant))


@router.post("/{capture_id}/commit", response_model=CaptureOut,
             responses={202: {"model": CaptureOut, "description": "Still validating"},
                        **error_responses(409)})
def commit_capture(capture_id: str, services: ServicesDep, tenant: TenantDep) -> JSONResponse:
    """Validate and freeze: 200 ready, 202 still validating (poll the capture), 409 files
    missing, 422 not a valid capture (the problems name each file; fix and commit again)."""
    c = get_capture(services.store, capture_id, tenant)
    committer = services.committer
    if begin_commit(services, c) or c.state == "committing":
        done = committer.start(c.id) if c.state != "committing" else committer.running(c.id)
        if done is not None:
            done.wait(services.settings.commit_wait_seconds)
    c = get_capture(services.store, capture_id, tenant)
    out = capture_out(services, c)
    if c.state == "uploading" and c.error:
        raise ApiError(commit_status(c.error), c.error["message"], code=c.error["code"],
                       retryable=c.error.get("retryable", False),
                       details=c.error.get("details", []))
    return JSONResponse(out.model_dump(mode="json"), status_code=200 if c.state == "ready" else 202)


@router.delete("/{capture_id}", status_code=204, responses={204: {"description": "Deleted"},
                                                            **error_responses(409)})
def delete_capture(capture_id: str, services: ServicesDep, tenant: TenantDep) -> Response:
    """Delete the capture, its staged files and its frozen copy (409 while a job uses it or it
    is being validated). Jobs made from it keep their results."""
    deleted(services.store.delete_capture(capture_id, tenant), "capture", capture_id)
    services.blobs.delete_prefix(f"captures/{capture_id}")
    services.staging.remove(capture_id)
    services.manifests.forget(capture_id)
    return Response(status_code=204)


@router.post("/archive", status_code=201, response_model=CaptureOut,
             responses=error_responses(400, 409, 413, 507),
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/zip": {"schema": {"type": "string", "format": "binary"}}}}})
async def upload_archive(request: Request, services: ServicesDep, tenant: TenantDep,
                         format: Format = "auto",
                         name: Annotated[Name, Query()] = "",
                         expires_at: AwareDatetime | None = None) -> JSONResponse:
    """A whole (small) capture as one zip body: checked, extracted, committed. 201 with the
    ready capture, or 4xx with nothing kept."""
    expiry = default_expiry(services, expires_at)
    tmp = services.staging.tmp_dir() / f"{secrets.token_hex(8)}.zip"
    try:
        await spool(request, tmp, services.settings.max_archive_bytes, "archive")
        out = await run(_commit_archive, services, tenant, tmp, format, name, expiry)
    finally:
        tmp.unlink(missing_ok=True)
    return _created(request, services, out)


def _commit_archive(services: Services, tenant: str, archive, fmt: str, name: str,
                    expires_at) -> CaptureOut:
    members = inspect_zip(archive, fmt, services.settings)
    capture_id = new_id("cap")
    try:
        manifest = extract(archive, members, services.staging.files_dir(capture_id))
        services.store.add_capture(Capture(
            id=capture_id, tenant=tenant, name=name, format=fmt, state="committing",
            manifest=manifest, total_bytes=sum(f["size"] for f in manifest),
            expires_at=expires_at, summary={OWNER_KEY: str(Owner.current())}))
        run_commit(services, capture_id)
        c = get_capture(services.store, capture_id, tenant)
        if c.state != "ready":
            error = c.error or {"code": "internal", "message": "commit failed"}
            raise ApiError(commit_status(error), error["message"],
                           code=error["code"], retryable=error.get("retryable", False),
                           details=error.get("details", []))
        return capture_out(services, c)
    except BaseException:
        services.store.remove_capture(capture_id)
        services.staging.remove(capture_id)
        services.blobs.delete_prefix(f"captures/{capture_id}")
        services.manifests.forget(capture_id)
        raise
