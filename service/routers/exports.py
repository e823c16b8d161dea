"""/v1/exports: a finished reconstruction delivered as the relightable sequence stream (the
web page's player fetches it by HTTP ranges), SPZ per frame or PLY per frame.

An export is a job of the `export` pipeline, the same shape as a render (202 + Location, the
job representation of /v1/jobs: events, logs, cancel, retry, artifacts under export/); it keeps
the reconstruction as `source_job_id`, which cannot be deleted while the export runs.
"""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from service.auth import TenantDep
from service.body import JsonRoute
from service.checks import check_export
from service.deps import ServicesDep
from service.errors import COMMON, error_responses
from service.idempotency import IdempotencyKey, Submit
from service.lookups import get_job
from service.routers.jobs import REPLAYED, accepted, queue_on_source
from service.schemas import ExportIn, JobOut
from worker.pipelines import makes_results, submitted_at

__all__ = ["router"]

router = APIRouter(prefix="/v1/exports", tags=["exports"], route_class=JsonRoute,
                   responses=error_responses(*COMMON))
PIPELINE = submitted_at(router.prefix)


@router.post("", status_code=202, response_model=JobOut,
             responses=error_responses(409, 413, 429), response_description=REPLAYED)
def request_export(body: ExportIn, services: ServicesDep, tenant: TenantDep,
                   idempotency_key: IdempotencyKey = None) -> JSONResponse:
    """Queue an export of a succeeded reconstruction (404 for a job that is not yours; 409 when
    it is not a succeeded reconstruction). With an Idempotency-Key, sending it again answers
    the same job. 429 as POST /v1/jobs."""
    submit = Submit(services, tenant, idempotency_key, "POST /v1/exports", body)
    if (first := submit.first()) is not None:
        return accepted(services, first, replayed=True)
    services.limits.admit(tenant)
    source = get_job(services.store, body.job_id, tenant)
    if makes_results(source.pipeline) and source.state == "succeeded":
        check_export(services, source, body)
    return queue_on_source(services, tenant, source, PIPELINE, body.params(), "exports", body,
                           submit)
