"""/v1/assets: inputs that are not captures: environment maps (equirectangular EXR or Radiance
HDR) for relight requests, and normal-prior models (TorchScript or ONNX) a reconstruction names
as its `normal_estimator`."""

from __future__ import annotations

import re
import secrets
from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import JSONResponse, StreamingResponse
from pydantic import AwareDatetime
from starlette.concurrency import run_in_threadpool as run

from service.auth import TenantDep
from service.body import JsonRoute
from service.deps import Services, ServicesDep, default_expiry, location
from service.envmap import CONTENT_TYPES, EnvmapError, inspect_envmap
from service.errors import COMMON, ApiError, error_responses
from service.lookups import deleted, get_asset
from service.modelfile import MODEL_CONTENT_TYPES, ModelFileError, inspect_model
from service.pagination import after, next_cursor
from service.ranges import blob_response
from service.schemas import AssetOut, AssetPage
from service.upload.archive import spool
from worker.models import Asset
from worker.pipelines import MODEL_KIND
from worker.store import new_id

__all__ = ["router"]

router = APIRouter(prefix="/v1/assets", tags=["assets"], route_class=JsonRoute,
                   responses=error_responses(*COMMON))
_FILENAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,200}$")
BINARY = {"content": {"application/octet-stream": {"schema": {"type": "string",
                                                              "format": "binary"}}}}


def asset_out(a: Asset) -> AssetOut:
    base = f"/v1/assets/{a.id}"
    return AssetOut(id=a.id, kind=a.kind, filename=a.filename, size=a.size, sha256=a.sha256,
                    content_type=a.content_type, width=a.meta.get("width", 0),
                    height=a.meta.get("height", 0), channels=a.meta.get("channels", 0),
                    sh9=a.meta.get("sh9"), created_at=a.created_at, expires_at=a.expires_at,
                    links={"self": base, "content": f"{base}/content"})


def _suffix(filename: str, kind: str) -> str:
    suffix = Path(filename).suffix.lower()
    known = CONTENT_TYPES if kind == "envmap" else MODEL_CONTENT_TYPES
    if not _FILENAME.match(filename) or suffix not in known:
        raise ApiError(422, f"filename: expected a plain file name ending in "
                            f"{' or '.join(known)} for a {kind} (letters, digits, '_', '-', "
                            f"'.'), got {filename!r}",
                       details=[{"path": "filename", "message": "invalid file name"}])
    return suffix


def _inspect(services: Services, tmp: Path, kind: str, filename: str,
             suffix: str) -> tuple[dict, str]:
    """(metadata, content type) of an uploaded file of `kind`; EnvmapError or ModelFileError
    saying what is wrong with it."""
    if kind == MODEL_KIND:
        return inspect_model(tmp, suffix), MODEL_CONTENT_TYPES[suffix]
    info = inspect_envmap(tmp, filename, services.settings.max_image_pixels)
    return ({"width": info.width, "height": info.height, "channels": info.channels,
             "sh9": info.sh9}, CONTENT_TYPES[suffix])


@router.post("", status_code=201, response_model=AssetOut, responses=error_responses(413),
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/octet-stream": {"schema": {"type": "string",
                                                         "format": "binary"}}}}})
async def upload_asset(request: Request, services: ServicesDep, tenant: TenantDep,
                       filename: Annotated[str, Query(min_length=1, max_length=200)],
                       kind: Literal["envmap", "normal_model"] = "envmap",
                       expires_at: AwareDatetime | None = None) -> JSONResponse:
    """Upload an environment map (.exr, .hdr) or a normal-prior model (`normal_model`:
    TorchScript .pt/.ts or .onnx) as the request body (checked; refused with the reason)."""
    suffix = _suffix(filename, kind)
    expiry = default_expiry(services, expires_at)
    tmp = services.staging.tmp_dir() / f"{secrets.token_hex(8)}{suffix}"
    try:
        size, sha = await spool(request, tmp, services.settings.max_asset_bytes, "asset")
        asset = await run(_store_asset, services, tenant, kind, filename, suffix, tmp, size,
                          sha, expiry)
    finally:
        tmp.unlink(missing_ok=True)
    out = asset_out(asset)
    return JSONResponse(out.model_dump(mode="json"), status_code=201, headers={
        "Location": location(services, out.links["self"])})


def _store_asset(services: Services, tenant: str, kind: str, filename: str, suffix: str,
                 tmp: Path, size: int, sha: str, expires_at) -> Asset:
    try:
        meta, content_type = _inspect(services, tmp, kind, filename, suffix)
    except EnvmapError as exc:
        raise ApiError(422, str(exc), code="invalid_asset",
                       details=[{"path": filename, "message": exc.problem}]) from None
    except ModelFileError as exc:
        raise ApiError(422, f"{filename}: {exc}", code="invalid_asset",
                       details=[{"path": filename, "message": str(exc)}]) from None
    asset = Asset(id=new_id("ast"), tenant=tenant, kind=kind, filename=filename, size=size,
                  sha256=sha, content_type=content_type, meta=meta, expires_at=expires_at)
    key = f"assets/{asset.id}/{filename}"
    try:
        services.blobs.put_file(key, tmp)
        services.store.add_asset(asset)
    except BaseException:
        services.blobs.delete_prefix(f"assets/{asset.id}")
        raise
    return asset


@router.get("", response_model=AssetPage)
def list_assets(services: ServicesDep, tenant: TenantDep,
                cursor: Annotated[str | None, Query(max_length=512)] = None,
                limit: Annotated[int, Query(ge=1, le=200)] = 50) -> AssetPage:
    """The caller's assets, newest first."""
    rows, last = services.store.asset_page(tenant, after(cursor), limit)
    return AssetPage(items=[asset_out(a) for a in rows], next_cursor=next_cursor(last))


@router.get("/{asset_id}", response_model=AssetOut)
def read_asset(asset_id: str, services: ServicesDep, tenant: TenantDep) -> AssetOut:
    return asset_out(get_asset(services.store, asset_id, tenant))


@router.get("/{asset_id}/content", response_class=StreamingResponse,
            responses={200: {"description": "The file", **BINARY},
                       206: {"description": "The requested range", **BINARY},
                       304: {"description": "Not modified (If-None-Match)"},
                       **error_responses(416)})
def asset_content(asset_id: str, request: Request, services: ServicesDep,
                  tenant: TenantDep) -> Response:
    """The file itself (Range, If-Range and If-None-Match as for artifacts)."""
    a = get_asset(services.store, asset_id, tenant)
    return blob_response(request, services.blobs, f"assets/{a.id}/{a.filename}", size=a.size,
                         sha256=a.sha256, content_type=a.content_type, filename=a.filename)


router.add_api_route("/{asset_id}/content", asset_content, methods=["HEAD"],
                     name="head_asset_content", response_class=StreamingResponse,
                     responses={200: {"description": "Headers of the file", "content": None},
                                206: {"description": "Headers of the range", "content": None},
                                304: {"description": "Not modified"}, **error_responses(416)})


@router.delete("/{asset_id}", status_code=204, responses={204: {"description": "Deleted"},
                                                          **error_responses(409)})
def delete_asset(asset_id: str, services: ServicesDep, tenant: TenantDep) -> Response:
    """Delete the asset and its file (409 while a queued or running job uses it)."""
    for each in deleted(services.store.delete_asset(asset_id, tenant), "asset", asset_id):
        services.blobs.delete_prefix(f"assets/{each}")
    return Response(status_code=204)
