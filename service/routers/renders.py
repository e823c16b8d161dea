"""/v1/renders: relit renders of a finished reconstruction under an environment map and lights.

A render is a job of the `relight` pipeline (202 + Location, the same job representation as a
reconstruction: follow it with /v1/jobs/{id}, its events, logs, cancel, retry and artifacts).
It runs on the reconstruction's results and capture, and keeps it as `source_job_id`: the
reconstruction cannot be deleted while the render is queued or running.
"""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from service.auth import TenantDep
from service.body import JsonRoute
from service.checks import check_render
from service.deps import ServicesDep
from service.errors import COMMON, ApiError, error_responses
from service.idempotency import IdempotencyKey, Submit
from service.lookups import get_asset, get_job
from service.routers.jobs import REPLAYED, accepted, queue_on_source
from service.schemas import JobOut, RenderIn
from worker.pipelines import makes_results, submitted_at

__all__ = ["router"]

router = APIRouter(prefix="/v1/renders", tags=["renders"], route_class=JsonRoute,
                   responses=error_responses(*COMMON))
PIPELINE = submitted_at(router.prefix)


@router.post("", status_code=202, response_model=JobOut,
             responses=error_responses(409, 413, 429), response_description=REPLAYED)
def request_render(body: RenderIn, services: ServicesDep, tenant: TenantDep,
                   idempotency_key: IdempotencyKey = None) -> JSONResponse:
    """Queue a relight job on a succeeded reconstruction under an envmap asset, a built-in map
    (builtin:NAME) or lights alone (404 for a job or envmap asset that is not yours; 409 when
    the job is not a succeeded reconstruction). With an Idempotency-Key, sending it again
    answers the same job. 429 as POST /v1/jobs."""
    submit = Submit(services, tenant, idempotency_key, "POST /v1/renders", body)
    if (first := submit.first()) is not None:
        return accepted(services, first, replayed=True)
    services.limits.admit(tenant)
    source = get_job(services.store, body.job_id, tenant)
    if body.envmap_asset is not None:
        asset = get_asset(services.store, body.envmap_asset, tenant)
        if asset.kind != "envmap":
            raise ApiError(422, f"envmap: asset {asset.id} is a {asset.kind}, not an envmap",
                           details=[{"path": "envmap", "message": "not an envmap asset"}])
    if makes_results(source.pipeline) and source.state == "succeeded":
        check_render(services, source, body)
    return queue_on_source(services, tenant, source, PIPELINE, body.params(), "renders", body,
                           submit)
