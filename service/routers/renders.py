"""/v1/renders: relit renders of a finished reconstruction under an environment map and lights.
The relighting pipeline lands with issue 7; until then a request that names objects the caller
owns is answered 501, so clients can be written against the final shape now."""

from __future__ import annotations

from fastapi import APIRouter

from service.auth import TenantDep
from service.deps import ServicesDep
from service.errors import COMMON, ApiError, error_responses
from service.records import get_asset, get_job
from service.schemas import RenderIn

__all__ = ["router"]

router = APIRouter(prefix="/v1/renders", tags=["renders"],
                   responses=error_responses(*COMMON))


@router.post("", status_code=202, responses=error_responses(501),
             response_description="Not yet: 501 until the relighting pipeline exists")
def request_render(body: RenderIn, services: ServicesDep, tenant: TenantDep) -> None:
    """Request relit renders (501 for now; 404 for a job or asset the caller does not own)."""
    get_job(services.store, body.job_id, tenant)
    if body.envmap is not None:
        asset = get_asset(services.store, body.envmap, tenant)
        if asset.kind != "envmap":
            raise ApiError(422, f"asset {asset.id} is a {asset.kind}, not an envmap")
    raise ApiError(501, "relighting lands with the relighting pipeline (issue 7); the job and "
                        "environment map are kept, so send this request again once "
                        "GET /v1/pipelines lists 'relight'", code="not_implemented")
