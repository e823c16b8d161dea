"""/v1/jobs/{id}/artifacts: what a job produced (typed: ply, render, normal, ao, depth, mesh,
metrics, ...), each downloadable with HTTP Range, and all of them as one streamed zip.

A download names an artifact by its path, which is looked up in the artifacts table: a client's
path is never joined onto a file system path."""

from __future__ import annotations

from typing import Annotated
from urllib.parse import quote

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import StreamingResponse

from service.auth import TenantDep
from service.body import JsonRoute
from service.deps import ServicesDep, location
from service.errors import COMMON, ApiError, error_responses
from service.lookups import get_job
from service.pagination import decode_cursor, encode_cursor
from service.ranges import blob_response
from service.schemas import ArtifactOut, ArtifactPage
from service.zipstream import ZipEntry, zip_stream

__all__ = ["router"]

router = APIRouter(prefix="/v1/jobs/{job_id}", tags=["artifacts"], route_class=JsonRoute,
                   responses=error_responses(*COMMON))
BINARY = {"content": {"application/octet-stream": {"schema": {"type": "string",
                                                              "format": "binary"}}}}


def _key(job_id: str, path: str) -> str:
    return f"jobs/{job_id}/artifacts/{path}"


@router.get("/artifacts", response_model=ArtifactPage)
def list_artifacts(job_id: str, request: Request, services: ServicesDep, tenant: TenantDep,
                   kind: Annotated[str | None, Query(max_length=32)] = None,
                   frame: Annotated[str | None, Query(max_length=64)] = None,
                   cursor: Annotated[str | None, Query(max_length=2048)] = None,
                   limit: Annotated[int, Query(ge=1, le=10_000)] = 1000) -> ArtifactPage:
    """The job's artifacts by path, optionally of one kind and one frame (also while it runs:
    finished frames are published as they complete)."""
    get_job(services.store, job_id, tenant)
    after = decode_cursor(cursor, (str,))[0] if cursor else None
    rows, last = services.store.artifact_page(job_id, kind=kind, frame=frame, after=after,
                                              limit=limit)
    base = f"/v1/jobs/{job_id}/artifacts/"
    items = [ArtifactOut(path=a.path, kind=a.kind, frame=a.frame, size=a.size, sha256=a.sha256,
                         content_type=a.content_type, created_at=a.created_at,
                         url=location(services, base + quote(a.path)))
             for a in rows]
    return ArtifactPage(items=items, next_cursor=None if last is None else encode_cursor(last))


@router.get("/artifacts.zip", response_class=StreamingResponse,
            responses={200: {"description": "Every artifact, one zip (stored, ZIP64)",
                             "content": {"application/zip": {"schema": {
                                 "type": "string", "format": "binary"}}}}})
def download_all(job_id: str, services: ServicesDep, tenant: TenantDep) -> StreamingResponse:
    """Every artifact of the job in one zip, streamed as it is written."""
    get_job(services.store, job_id, tenant)
    entries = [ZipEntry(a.path, _key(job_id, a.path), a.size, a.created_at)
               for a in services.store.artifacts(job_id)]
    return StreamingResponse(zip_stream(services.blobs, entries), media_type="application/zip",
                             headers={"Content-Disposition":
                                      f'attachment; filename="{job_id}.zip"'})


@router.get("/artifacts/{path:path}", response_class=StreamingResponse,
            responses={200: {"description": "The file", **BINARY},
                       206: {"description": "The requested range", **BINARY},
                       304: {"description": "Not modified (If-None-Match)"},
                       **error_responses(416)})
def download_artifact(job_id: str, path: str, request: Request, services: ServicesDep,
                      tenant: TenantDep) -> Response:
    """One artifact; Range, If-Range and If-None-Match are honoured (ETag: its SHA-256)."""
    get_job(services.store, job_id, tenant)
    row = services.store.artifact(job_id, path)
    if row is None:
        raise ApiError(404, f"job {job_id} has no artifact {path!r}")
    return blob_response(request, services.blobs, _key(job_id, row.path), size=row.size,
                         sha256=row.sha256, content_type=row.content_type,
                         filename=row.path.rsplit("/", 1)[-1])


router.add_api_route("/artifacts/{path:path}", download_artifact, methods=["HEAD"],
                     name="head_artifact", response_class=StreamingResponse,
                     responses={200: {"description": "Headers of the file", "content": None},
                                206: {"description": "Headers of the range", "content": None},
                                304: {"description": "Not modified"}, **error_responses(416)})
