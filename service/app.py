"""The FastAPI application: `create_app(settings)` migrates the job store, opens the artifact
store and the Celery client, and mounts one router per resource (docs/design.md 3.5)."""

from __future__ import annotations

from fastapi import Depends, FastAPI
from fastapi.middleware.cors import CORSMiddleware

from service.deps import Services
from service.errors import install_error_handlers
from service.limits import Limits
from service.middleware import EXPOSED, strict_query
from service.routers import artifacts, assets, captures, exports, info, jobs, renders, uploads
from service.routers.info import package_version
from service.settings import ServiceSettings, get_service_settings
from service.upload.commit import Committer, recover_commits
from service.upload.staging import ManifestCache, Staging
from service.upload.tus import HashCache
from service.webpage import mount_web
from worker.blobs import open_store
from worker.celery_app import make_celery
from worker.db import migrate
from worker.store import JobStore

__all__ = ["build_services", "create_app"]

DESCRIPTION = """Relightable volumetric video as a service: upload a multi-camera capture
(resumable tus uploads, or one zip), run reconstruction jobs on it, follow their progress,
download the results (HTTP Range, or everything as one zip).

Authenticate with `Authorization: Bearer <API key>` (keys: `dgs keys create`). Errors are
`{"error": {"code", "message", "retryable", "details"}}` with a real HTTP status."""

def build_services(settings: ServiceSettings) -> Services:
    store = JobStore(settings.database)
    services = Services(
        settings=settings, store=store,
        blobs=open_store(settings.storage, endpoint_url=settings.s3_endpoint_url,
                         region=settings.s3_region),
        celery=make_celery(settings), staging=Staging(settings.data_dir / "uploads"),
        manifests=ManifestCache(store), hashes=HashCache(),
        limits=Limits(settings, store))
    services.committer = Committer(services)
    return services


def create_app(settings: ServiceSettings | None = None) -> FastAPI:
    """The API on `settings` (default: from the environment). Migrates the job store first."""
    settings = settings or get_service_settings()
    migrate(settings.database)
    services = build_services(settings)
    recover_commits(services)
    app = FastAPI(title="dgs", version=package_version(), description=DESCRIPTION,
                  generate_unique_id_function=lambda route: route.name,
                  dependencies=[Depends(strict_query)],
                  openapi_tags=[{"name": n} for n in ("info", "captures", "uploads", "jobs",
                                                      "artifacts", "assets", "renders", "exports")])
    app.state.services = services
    install_error_handlers(app)
    for module in (info, captures, uploads, jobs, artifacts, assets, renders, exports):
        app.include_router(module.router)
    mount_web(app)  # the web page at / (after the API, which it never shadows)
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins,
                           allow_methods=["*"], allow_headers=["*"], expose_headers=EXPOSED,
                           max_age=3600)
    return app
