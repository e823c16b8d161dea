"""/v1/exports: a finished reconstruction delivered as the relightable sequence stream (the
web page's player fetches it by HTTP ranges), SPZ per frame or PLY per frame.

An export is a job of the `export` pipeline, the same shape as a render (202 + Location, the
job representation of /v1/jobs: events, logs, cancel, retry, artifacts under export/); it keeps
the reconstruction as `source_job_id`, which cannot be deleted while the export runs.
"""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from service.auth import TenantDep
from service.body import JsonRoute
from service.checks import check_export
from service.deps import ServicesDep
from service.errors import COMMON, error_responses
from service.records import get_job
from service.routers.jobs import queue_on_source
from service.schemas import ExportIn, JobOut

__all__ = ["router"]

router = APIRouter(prefix="/v1/exports", tags=["exports"], route_class=JsonRoute,
                   responses=error_responses(*COMMON))


@router.post("", status_code=202, response_model=JobOut, responses=error_responses(409, 413),
             response_description="The export job, queued (Location names it)")
def request_export(body: ExportIn, request: Request, services: ServicesDep,
                   tenant: TenantDep) -> JSONResponse:
    """Queue an export of a succeeded reconstruction (404 for a job that is not yours; 409 when
    it is not a succeeded reconstruction)."""
    source = get_job(services.store, body.job_id, tenant)
    if source.pipeline == "reconstruct" and source.state == "succeeded":
        check_export(services, source, body)
    return queue_on_source(request, services, tenant, source, "export", body.params(),
                           "exports", body)
