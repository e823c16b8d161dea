"""A job's parameters checked against what only the server knows, before the job is made: the
capture's frames and cameras, the devices this deployment offers, the tenant's own model assets
and the operator's allow-list; and a reconstruction's run resolved against its capture
(`core.config.resolve_run`, the rules the worker and the command line follow), which the job
stores. Every refusal is a 422 naming the parameter; nothing a request sends is ever opened as
a file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from core.config import ConfigError, ResolvedRun, parse_frames
from core.data.capture import Capture as CaptureLayout
from core.data.schema import parse_capture_json
from service.deps import Services
from service.errors import ApiError
from worker.models import Capture, Job
from worker.pipelines import (
    MODEL_KIND,
    ExportJobParams,
    Pipeline,
    ReconstructParams,
    RelightJobParams,
)

__all__ = ["check_export", "check_params", "check_reconstruct", "check_render", "refuse"]


def refuse(path: str, message: str) -> ApiError:
    """A 422 whose message and single detail name `path`."""
    return ApiError(422, f"{path}: {message}", details=[{"path": path, "message": message}])


def _frame_ids(count: int) -> list[str]:
    return [str(i) for i in range(count)]


def _frames(spec: str | None, count: int, path: str, what: str) -> list[str]:
    try:
        return parse_frames(spec, _frame_ids(count))
    except ValueError:
        raise refuse(path, f"{spec!r} selects no frame of the {count} in the {what} (a Python "
                           f"slice over 0..{count - 1}, e.g. '0:{count}')") from None


def check_params(pipeline: Pipeline, params: BaseModel) -> None:
    """The pipeline's own checks across its parameters (a reconstruction's configuration
    resolves): 422 with a detail per bad setting, under `params.`."""
    if pipeline.check is None:
        return
    try:
        pipeline.check(params)
    except ValueError as exc:
        raise _refused(exc) from None


def _refused(exc: ValueError) -> ApiError:
    """A 422 with a detail per problem of a job's parameters (`ConfigError.details`; paths
    under `params.`)."""
    problems = getattr(exc, "details", None) or [{"path": "", "message": str(exc)}]
    details = [{"path": f"params.{d['path']}", "message": d["message"]} for d in problems]
    return ApiError(422, f"{details[0]['path']}: {details[0]['message']}", details=details)


def _layout(services: Services, capture: Capture) -> CaptureLayout:
    """The capture's frozen capture.json, parsed (the API never opens its other files)."""
    key = f"captures/{capture.id}/capture.json"
    size = services.blobs.size(key)
    if size is None:
        raise ApiError(409, f"capture {capture.id} has no capture.json in the store; upload "
                            "and commit it again")
    data = json.loads(b"".join(services.blobs.read_range(key, 0, size)))
    layout, problems = parse_capture_json(data, Path(capture.id))
    if layout is None:  # it was valid when committed: the store changed under it
        raise ApiError(409, f"capture {capture.id}: {problems[0].message}; commit it again")
    return layout


def check_reconstruct(services: Services, tenant: str, capture: Capture,
                      params: ReconstructParams) -> ResolvedRun:
    """The frames exist, the devices are offered and the normal estimator is one the tenant
    may use (`check_params` has resolved the configuration); returns the run resolved against
    the capture, which the job stores (422 naming `params.config.split` when the split leaves
    no camera to train on, `params.config.mesh.subject` when the capture has no masks)."""
    cfg = params.run_config()
    summary = capture.summary or {}
    if "frames" in summary:
        _frames(params.frames, int(summary["frames"]), "params.frames", "capture")
    offered = services.settings.offered_devices
    for path, device in (("params.config.train.device", cfg.train.device),
                         ("params.config.mesh.device", cfg.mesh.device)):
        if device is not None and device not in offered:
            raise refuse(path, f"{device!r} is not offered by this deployment (offered: "
                               f"{', '.join(offered)})")
    if cfg.normal_estimator is not None:
        _check_model(services, tenant, cfg.normal_estimator)
    try:
        return params.resolve(_layout(services, capture), capture_name=capture.id,
                              has_masks=summary.get("masks", 1) > 0)
    except ConfigError as exc:
        raise _refused(exc) from None


def _check_model(services: Services, tenant: str, name: str) -> None:
    allowed = services.settings.normal_estimators
    if name in allowed:
        return
    asset = services.store.asset(name, tenant)
    if asset is not None and asset.kind == MODEL_KIND:
        return
    served = ", ".join(sorted(allowed)) or "none configured"
    what = (f"asset {name} is a {asset.kind}, not a {MODEL_KIND}" if asset is not None
            else f"{name!r} is neither a {MODEL_KIND} asset of yours nor a model this server "
                 f"offers")
    raise refuse("params.config.normal_estimator",
                 f"{what}; upload the model with POST /v1/assets?kind={MODEL_KIND} and give its "
                 f"id, or name one of the server's models ({served})")


def _source_summary(services: Services, source: Job) -> dict[str, Any]:
    """The summary of the capture a reconstruction was made from (empty once deleted)."""
    if source.capture_id is None:
        return {}
    return services.store.capture_summary(source.capture_id)


def _check_source_frames(source: Job, summary: dict[str, Any], spec: str | None) -> None:
    """`spec` (a request's `frames`) selects some of the frames the reconstruction made."""
    if "frames" in summary:
        made = _frames(source.params.get("frames"), int(summary["frames"]), "params.frames",
                       "capture")
        _frames(spec, len(made), "frames", f"reconstruction {source.id}")


def check_export(services: Services, source: Job, params: ExportJobParams) -> None:
    """The frames are among the reconstruction's; a subject export needs masks to find the
    subject by."""
    summary = _source_summary(services, source)
    _check_source_frames(source, summary, params.frames)
    if params.subject and summary.get("masks") == 0:
        raise refuse("subject", "the capture has no masks, so nothing says where the subject "
                                "is; export the whole scene")


def check_render(services: Services, source: Job, params: RelightJobParams) -> None:
    """The frames are among the reconstruction's and the cameras among its capture's."""
    summary = _source_summary(services, source)
    _check_source_frames(source, summary, params.frames)
    ids = summary.get("camera_ids")
    if params.orbit is None and params.cameras not in ("heldout", "all") and ids is not None:
        asked = [c.strip() for c in params.cameras.split(",")]
        unknown = [c for c in asked if c not in ids]
        if unknown or not any(asked):
            shown = ", ".join(ids[:12]) + (", ..." if len(ids) > 12 else "")
            raise refuse("cameras", f"no camera {unknown[0] if unknown else '(empty)'!r} in "
                                    f"the capture (heldout, all, or ids among: {shown})")
