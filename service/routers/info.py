"""Health, readiness, what this server offers (/v1/info) and its pipelines' parameters as JSON
Schema (/v1/pipelines)."""

from __future__ import annotations

import concurrent.futures
from importlib.metadata import PackageNotFoundError, version

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from core.data.importers import IMPORTERS
from service.auth import TenantDep, has_active_key
from service.body import JsonRoute
from service.deps import Services, ServicesDep
from service.errors import error_responses
from service.server_info import HealthOut, InfoOut, LimitsOut, PipelineOut, ReadyOut, TusOut
from service.upload.tus import ALGORITHMS, EXTENSIONS, TUS_VERSION
from worker.pipelines import PIPELINES

__all__ = ["router"]

router = APIRouter(tags=["info"], route_class=JsonRoute)
CHECK_SECONDS = 3.0
_checks = concurrent.futures.ThreadPoolExecutor(max_workers=2, thread_name_prefix="readyz")


def package_version() -> str:
    try:
        return version("dgs")
    except PackageNotFoundError:
        return "0+unknown"


@router.get("/healthz", response_model=HealthOut)
def healthz() -> HealthOut:
    """Liveness: the process answers (no key needed)."""
    return HealthOut(status="ok")


def _database(services: Services) -> None:
    services.store.ping()


def _broker(services: Services) -> None:
    with services.celery.connection_for_write() as conn:
        conn.ensure_connection(max_retries=1, interval_start=0, timeout=CHECK_SECONDS)


@router.get("/readyz", response_model=ReadyOut,
            responses={503: {"model": ReadyOut, "description": "A dependency is unreachable"}})
def readyz(services: ServicesDep) -> JSONResponse:
    """Readiness: the job store and the broker answer (503 otherwise; no key needed)."""
    futures = {name: _checks.submit(fn, services)
               for name, fn in (("database", _database), ("broker", _broker))}
    checks = {}
    for name, future in futures.items():
        try:
            future.result(timeout=CHECK_SECONDS + 1)
            checks[name] = "ok"
        except Exception as exc:  # whatever the driver raises, the answer is "not ready"
            checks[name] = f"error: {type(exc).__name__}"
    ready = all(v == "ok" for v in checks.values())
    out = ReadyOut(status="ready" if ready else "unavailable", checks=checks)
    return JSONResponse(out.model_dump(), status_code=200 if ready else 503)


@router.get("/v1/info", response_model=InfoOut, responses=error_responses(401, 500))
def info(services: ServicesDep, tenant: TenantDep) -> InfoOut:
    """Version, limits, the tus endpoint, pipelines, and the caller's jobs per state."""
    s = services.settings
    counts = services.store.job_counts(tenant)
    return InfoOut(
        version=package_version(), tenant=tenant,
        keys_required=has_active_key(services.store.url),
        limits=LimitsOut(**{k: getattr(s, k) for k in LimitsOut.model_fields}),
        tus=TusOut(endpoint="/v1/uploads", version=TUS_VERSION, extensions=list(EXTENSIONS),
                   checksum_algorithms=sorted(ALGORITHMS), max_size=s.max_file_bytes),
        pipelines=sorted(PIPELINES),
        capture_formats={name: i.summary for name, i in IMPORTERS.items()},
        jobs={state: int(counts.get(state, 0)) for state in
              ("queued", "running", "succeeded", "failed", "cancelled")},
        retention_days=s.retention_days)


@router.get("/v1/pipelines", response_model=list[PipelineOut],
            responses=error_responses(401, 500))
def pipelines(tenant: TenantDep) -> list[PipelineOut]:
    """Each pipeline with its parameters as JSON Schema and the artifact kinds it produces."""
    return [PipelineOut(name=p.name, description=p.description, params_schema=p.schema(),
                        artifact_kinds=list(p.artifacts)) for p in PIPELINES.values()]
