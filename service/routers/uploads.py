"""/v1/uploads: tus 1.0.0 resumable uploads, one per manifest file (core, creation,
termination, checksum), so standard clients (tuspy, tus-js-client, Uppy) upload and resume.

Creation metadata: `capture` (the capture id) and `path` (the manifest path; `filename` is
accepted instead). Bodies are written and hashed in blocks of about 4 MiB in a worker thread
while the event loop receives the next block, so a slow disk never blocks the event loop.
"""

from __future__ import annotations

import asyncio
import base64
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Request, Response
from starlette.concurrency import run_in_threadpool as run
from starlette.requests import ClientDisconnect

from service.auth import TenantDep
from service.body import JsonRoute, content_length
from service.deps import Services, ServicesDep, location
from service.errors import COMMON, ApiError, error_responses
from service.lookups import get_upload
from service.upload.files import (
    complete_upload,
    create_upload,
    record_offset,
    require_uploading,
    terminate_upload,
)
from service.upload.tus import (
    ALGORITHMS,
    EXTENSIONS,
    OFFSET_TYPE,
    TUS_VERSION,
    PartLock,
    PartWriter,
    parse_checksum,
    parse_length,
    parse_metadata,
    tus_headers,
)
from worker.models import Upload

__all__ = ["router"]

WRITE_CHUNK = 4 << 20


def require_tus(tenant: TenantDep,
                tus_resumable: Annotated[str | None, Header()] = None) -> None:
    """412 unless the client speaks tus 1.0.0 (after authentication: who asks comes first)."""
    if tus_resumable != TUS_VERSION:
        raise ApiError(412, f"Tus-Resumable: this server speaks tus {TUS_VERSION}, got "
                            f"{tus_resumable!r}", headers={"Tus-Version": TUS_VERSION})


router = APIRouter(prefix="/v1/uploads", tags=["uploads"], route_class=JsonRoute,
                   responses=error_responses(*COMMON, 412))
Tus = Depends(require_tus)
NO_CONTENT = {"description": "Done (tus headers only)", "content": None}


@router.options("", status_code=204, responses={204: NO_CONTENT})
def tus_options(services: ServicesDep) -> Response:
    """What this tus server supports (no key needed, like a CORS pre-flight)."""
    return Response(status_code=204, headers=tus_headers(
        Tus_Version=TUS_VERSION, Tus_Extension=",".join(EXTENSIONS),
        Tus_Max_Size=services.settings.max_file_bytes,
        Tus_Checksum_Algorithm=",".join(sorted(ALGORITHMS))))


@router.post("", status_code=201, dependencies=[Tus],
             responses={201: NO_CONTENT, **error_responses(409, 413, 422, 460)})
def tus_create(request: Request, services: ServicesDep, tenant: TenantDep,
           upload_length: Annotated[str | None, Header()] = None,
           upload_metadata: Annotated[str | None, Header()] = None) -> Response:
    """Start the upload of one manifest file; Location is where to PATCH its bytes."""
    if request.headers.get("upload-defer-length"):
        raise ApiError(400, "Upload-Defer-Length is not supported; the manifest knows the size")
    length = parse_length(upload_length, "Upload-Length")
    meta = parse_metadata(upload_metadata)
    capture_id = meta.get("capture")
    path = meta.get("path") or meta.get("filename")
    if not capture_id or not path:
        raise ApiError(400, "Upload-Metadata must name the capture ('capture') and the file's "
                            "manifest path ('path')")
    upload = create_upload(services, tenant, capture_id, path, length)
    url = location(services, f"/v1/uploads/{upload.id}")
    return Response(status_code=201, headers=tus_headers(Location=url, Upload_Offset=0))


def _metadata(upload: Upload) -> str:
    enc = [(k, base64.b64encode(v.encode()).decode())
           for k, v in (("capture", upload.capture_id), ("path", upload.path))]
    return ",".join(f"{k} {v}" for k, v in enc)


@router.head("/{upload_id}", status_code=200, dependencies=[Tus],
             responses={200: {"description": "Upload-Offset and Upload-Length", "content": None}})
def tus_head(upload_id: str, services: ServicesDep, tenant: TenantDep) -> Response:
    """How far the upload got: resume with PATCH at Upload-Offset."""
    upload = get_upload(services.store, upload_id, tenant)
    if upload.state == "corrupt":
        raise ApiError(404, f"upload {upload_id} failed its checksum and was dropped; create a "
                            "new upload")
    offset = upload.length if upload.state in ("received", "duplicate") else upload.offset
    return Response(status_code=200, headers=tus_headers(
        Upload_Offset=offset, Upload_Length=upload.length, Cache_Control="no-store",
        Upload_Metadata=_metadata(upload)))


@router.patch("/{upload_id}", status_code=204, dependencies=[Tus],
              responses={204: NO_CONTENT, **error_responses(409, 413, 415, 460)},
              openapi_extra={"requestBody": {"required": True, "content": {
                  OFFSET_TYPE: {"schema": {"type": "string", "format": "binary"}}}}})
async def tus_patch(upload_id: str, request: Request, services: ServicesDep, tenant: TenantDep,
                    upload_offset: Annotated[str | None, Header()] = None,
                    upload_checksum: Annotated[str | None, Header()] = None) -> Response:
    """Append bytes at Upload-Offset; with Upload-Checksum they are kept only if they match."""
    if (request.headers.get("content-type") or "").split(";")[0].strip() != OFFSET_TYPE:
        raise ApiError(415, f"Content-Type must be {OFFSET_TYPE}")
    offset = parse_length(upload_offset, "Upload-Offset")
    checksum = parse_checksum(upload_checksum)
    upload = await run(get_upload, services.store, upload_id, tenant)
    lock = PartLock(services.staging.lock(upload.capture_id, upload.id))
    await run(lock.acquire)
    try:
        upload = await run(get_upload, services.store, upload_id, tenant)  # as of the lock
        new_offset = await _receive(request, services, upload, offset, checksum, tenant)
    finally:
        lock.release()
    return Response(status_code=204, headers=tus_headers(Upload_Offset=new_offset))


async def _refuse_past_end(request: Request, upload: Upload) -> None:
    """413 when a PATCH at the end of a complete upload carries bytes: they would pass
    Upload-Length, and dropping them silently would tell the client they were kept."""
    declared = content_length(request)
    extra = declared is not None and declared > 0
    if not extra and declared is None:  # chunked: look at what arrives
        async for chunk in request.stream():
            if chunk:
                extra = True
                break
    if extra:
        raise ApiError(413, f"upload {upload.id} is complete ({upload.length} bytes); the "
                            "body's bytes would pass Upload-Length and were refused",
                       headers=tus_headers(Upload_Offset=upload.length))


def _check_patch(request: Request, upload: Upload, offset: int) -> None:
    if upload.state == "corrupt":
        raise ApiError(409, f"upload {upload.id} failed its checksum; create a new upload")
    if upload.state != "receiving":
        raise ApiError(409, f"upload {upload.id} is complete ({upload.length} bytes)",
                       headers=tus_headers(Upload_Offset=upload.length))
    if offset != upload.offset:
        raise ApiError(409, f"Upload-Offset {offset} does not match the upload's offset "
                            f"{upload.offset}; HEAD it and resume from there",
                       headers=tus_headers(Upload_Offset=upload.offset))
    declared = content_length(request)
    if declared is not None and offset + declared > upload.length:
        raise ApiError(413, f"{declared} bytes at offset {offset} would pass Upload-Length "
                            f"{upload.length}")


async def _receive(request: Request, services: Services, upload: Upload, offset: int,
                   checksum: tuple[str, bytes] | None, tenant: str) -> int:
    """Write the body at `offset`; returns the new offset. Raises ApiError 460 for a bad
    checksum (the body is dropped) and completes the upload at its last byte."""
    if upload.state in ("received", "duplicate") and offset == upload.length:
        await _refuse_past_end(request, upload)
        return upload.length  # a client resuming (HEAD, then PATCH) after the last byte
    _check_patch(request, upload, offset)
    await run(require_uploading, services, upload.capture_id, tenant)
    part = services.staging.part(upload.capture_id, upload.id)
    sha = await run(services.hashes.take, upload.id, offset, part)
    start_sha = sha.copy() if checksum else None
    check = ALGORITHMS[checksum[0]]() if checksum else None
    writer = await run(PartWriter, part, offset, sha, check)
    try:
        await _stream_body(request, services, upload, writer, checksum is not None)
        if checksum is not None:
            await run(writer.flush)
            if check.digest() != checksum[1]:
                received = writer.received  # before the rewind drops them
                await run(writer.rewind, offset)
                services.hashes.keep(upload.id, offset, start_sha)
                raise ApiError(460, f"Upload-Checksum: the {checksum[0]} of the "
                                    f"{received} bytes sent does not match; they were "
                                    "dropped, send them again", retryable=True)
        new_offset = await run(writer.sync)
    except ClientDisconnect:
        # The client is gone: keep what arrived (unless it cannot be checked), so it resumes.
        if checksum is not None:
            await run(writer.rewind, offset)
            sha, new_offset = start_sha, offset
        else:
            new_offset = await run(writer.sync)
    except BaseException:
        # Also on cancellation, where awaiting is not possible: a truncate and a close are
        # quick enough to run here.
        writer.rewind(writer.synced)
        raise
    finally:
        writer.close()
    if new_offset == upload.length:
        await run(complete_upload, services, upload, sha.hexdigest())
        return new_offset
    await run(record_offset, services, upload.id, new_offset)
    services.hashes.keep(upload.id, new_offset, sha)
    return new_offset


async def _stream_body(request: Request, services: Services, upload: Upload,
                       writer: PartWriter, checked: bool) -> None:
    """Receive the body into `writer`: each WRITE_CHUNK block is written and hashed in a worker
    thread while the next one arrives (at most one in flight, so memory stays at two blocks).
    Unchecked bodies are made durable every `upload_sync_bytes` by an fsync that also runs
    beside the receiving (the offset it covers is recorded when it returns), so a dropped
    connection or a crash keeps what was synced."""
    sync_every = services.settings.upload_sync_bytes
    inflight: asyncio.Future | None = None
    syncing: asyncio.Future | None = None
    last_sync = writer.synced

    async def durable(offset: int) -> None:
        await run(writer.sync_to, offset)
        await run(record_offset, services, upload.id, offset)

    try:
        async for chunk in request.stream():
            if writer.start + writer.received + len(chunk) > upload.length:
                raise ApiError(413, f"the body passes Upload-Length {upload.length}; the "
                                    "request was refused (HEAD gives the offset kept)")
            writer.add(chunk)
            if writer.buffered >= WRITE_CHUNK:
                if inflight is not None:
                    await inflight
                inflight = asyncio.ensure_future(run(writer.write, writer.take()))
            if (not checked and writer.offset - last_sync >= sync_every
                    and (syncing is None or syncing.done())):
                if syncing is not None:
                    syncing.result()  # a failed fsync ends the request here
                last_sync = writer.offset  # written (not in flight): what this fsync covers
                syncing = asyncio.ensure_future(durable(last_sync))
    finally:
        # Whatever happens next (a flush, a sync, a rewind) needs the block written and the
        # fsync done first; shielded, so that a cancelled request still waits for the threads
        # it started.
        for pending in (inflight, syncing):
            if pending is not None:
                await asyncio.shield(pending)


@router.delete("/{upload_id}", status_code=204, dependencies=[Tus],
               responses={204: NO_CONTENT, **error_responses(409)})
def tus_delete(upload_id: str, services: ServicesDep, tenant: TenantDep) -> Response:
    """tus termination: the upload's bytes are removed (a received file stays: 409)."""
    upload = get_upload(services.store, upload_id, tenant)
    lock = PartLock(services.staging.lock(upload.capture_id, upload.id))
    lock.acquire()
    try:
        terminate_upload(services, get_upload(services.store, upload_id, tenant))
    finally:
        lock.release()
    return Response(status_code=204, headers=tus_headers())
