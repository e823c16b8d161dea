"""/v1/jobs: run a pipeline on a ready capture, follow it (polling, server-sent events, logs),
cancel it, retry it from its last checkpoint, delete it."""

from __future__ import annotations

import logging
import shutil
from typing import Annotated

from fastapi import APIRouter, Header, Query, Response
from fastapi.responses import JSONResponse, StreamingResponse
from pydantic import BaseModel

from core.config import ConfigError
from service.auth import TenantDep
from service.body import JsonRoute
from service.checks import check_params, check_reconstruct
from service.deps import Services, ServicesDep, default_expiry, location
from service.errors import COMMON, ApiError, ErrorInfo, error_responses
from service.events import job_events
from service.idempotency import IdempotencyKey, Submit
from service.limits import HeldStream, cap_refused
from service.lookups import deleted, get_capture, get_job
from service.pagination import after, next_cursor
from service.parts import job_parts, split_job
from service.schemas import JobIn, JobOut, JobPage, JobState, LogsOut, ProgressOut
from worker.celery_app import dispatch
from worker.models import Job
from worker.parts import worker_of
from worker.pipelines import Pipeline, get_pipeline, makes_results
from worker.store import ACTIVE, TERMINAL, CapReached, NotCreated, progress_of

__all__ = ["REPLAYED", "accepted", "job_out", "queue_on_source", "router", "send"]

log = logging.getLogger("dgs.service")
REPLAYED = ("The job, queued (Location names it); with an Idempotency-Key already used for the "
            "same request, the job that request made, whatever its state (header "
            "Idempotent-Replayed: true)")
router = APIRouter(prefix="/v1/jobs", tags=["jobs"], route_class=JsonRoute,
                   responses=error_responses(*COMMON))


def job_out(job: Job, services: Services | None = None) -> JobOut:
    """The job as the API shows it; with `services`, a job run as parts lists them."""
    base = f"/v1/jobs/{job.id}"
    parts, progress = job_parts(services, job) if services is not None else (None,
                                                                              progress_of(job))
    return JobOut(
        id=job.id, name=job.name, capture_id=job.capture_id, source_job_id=job.source_job_id,
        pipeline=job.pipeline, parts=parts,
        params=job.params, state=job.state, progress=ProgressOut(**progress),
        error=ErrorInfo(**job.error) if job.error else None, attempts=job.attempts,
        worker=worker_of(job), runs=job.runs or [],
        cancel_requested=job.cancel_requested, created_at=job.created_at,
        updated_at=job.updated_at, started_at=job.started_at, finished_at=job.finished_at,
        expires_at=job.expires_at,
        links={"self": base, "events": f"{base}/events", "logs": f"{base}/logs",
               "artifacts": f"{base}/artifacts", "archive": f"{base}/artifacts.zip",
               "cancel": f"{base}/cancel", "retry": f"{base}/retry"})


def accepted(services: Services, job: Job, *, replayed: bool = False) -> JSONResponse:
    """202 with the job and its Location; `replayed`: the job an Idempotency-Key made before
    (header Idempotent-Replayed: true)."""
    out = job_out(job, services)
    headers = {"Location": location(services, out.links["self"])}
    if replayed:
        headers["Idempotent-Replayed"] = "true"
    return JSONResponse(out.model_dump(mode="json"), status_code=202, headers=headers)


def send(services: Services, job: Job) -> None:
    """Hand the job to the broker. When the broker is away the job stays queued and
    undispatched; the sweeper sends it once the broker is back."""
    services.store.mark_dispatched(job.id)
    try:
        dispatch(services.celery, services.settings, job.id, job.pipeline)
    except Exception:
        log.exception("job %s: the broker refused it; the sweeper will send it again", job.id)
        services.store.undispatch(job.id)


def queue_on_source(services: Services, tenant: str, source: Job, pipeline: Pipeline,
                    params: dict, what: str, body, submit: Submit) -> JSONResponse:
    """Queue a job of `pipeline` on the results of `source`, a succeeded reconstruction of
    `tenant` (409 otherwise, retryable while it runs; 404 when it is deleted meanwhile):
    renders and exports (`what`: "renders", "exports"), kept with `submit`'s key; 429 past
    the tenant's active-jobs cap."""
    if not makes_results(source.pipeline):
        raise ApiError(409, f"job {source.id} is a {source.pipeline} job; {what} are made from "
                            "a reconstruct job")
    if source.state != "succeeded":
        running = source.state in ("queued", "running")
        raise ApiError(409, f"job {source.id} is {source.state}; {what} are made from a "
                            "succeeded reconstruction" + (" (wait for it to end)" if running
                                                          else ""), retryable=running)
    services.limits.change(tenant)
    try:
        job = services.store.create_render(tenant, source.id, pipeline.name, params,
                                           name=body.name,
                                           expires_at=default_expiry(services, body.expires_at),
                                           idempotency=submit.idempotency,
                                           cap=services.settings.max_active_jobs)
    except (NotCreated, CapReached) as exc:  # a submit with the same key made its job first
        if (first := submit.first()) is not None:
            return accepted(services, first, replayed=True)
        if isinstance(exc, CapReached):
            raise cap_refused(exc) from None
        raise
    if job is None:  # deleted meanwhile
        raise ApiError(404, f"no job {body.job_id!r}")
    send(services, job)
    return accepted(services, job)


def _params(pipeline_name: str, params: dict) -> BaseModel:
    try:
        pipeline = get_pipeline(pipeline_name)
        if pipeline.source != "capture":
            raise ValueError(f"pipeline: {pipeline.name} runs on a finished job, not on a "
                             f"capture; request it with POST {pipeline.endpoint}")
    except ValueError as exc:
        raise ApiError(422, str(exc), details=[{"path": "pipeline", "message": str(exc)}]) from None
    try:
        model = pipeline.parse(params, "params")
    except ConfigError as exc:
        raise ApiError(422, str(exc), details=exc.details) from None
    check_params(pipeline, model)
    return model


@router.post("", status_code=202, response_model=JobOut,
             responses=error_responses(409, 413, 429), response_description=REPLAYED)
def create_job(body: JobIn, services: ServicesDep, tenant: TenantDep,
               idempotency_key: IdempotencyKey = None) -> JSONResponse:
    """Queue a pipeline run on a ready capture (202; Location is the job). Every parameter is
    checked first, against the capture too (its frames), the devices this deployment offers
    and the models the tenant may use: 422 naming each bad one, and no job is made. With an
    Idempotency-Key, sending it again answers the same job (never refused by the limits).
    429 with Retry-After past the tenant's rate of job changes or its active-jobs cap."""
    submit = Submit(services, tenant, idempotency_key, "POST /v1/jobs", body)
    if (first := submit.first()) is not None:
        return accepted(services, first, replayed=True)
    services.limits.admit(tenant)
    params = _params(body.pipeline, body.params)
    capture = get_capture(services.store, body.capture_id, tenant)
    if capture.state != "ready":
        raise ApiError(409, f"capture {capture.id} is {capture.state}; commit it first "
                            "(POST /v1/captures/{id}/commit)")
    # The run, resolved once against the capture: the job stores it and its worker runs it.
    resolved = check_reconstruct(services, tenant, capture, params)
    # A sequence of several groups of pictures runs as parts, one per group, on any idle
    # workers (docs/design.md 4.4); the parent is sent once they have all succeeded.
    groups = split_job(resolved)
    expires_at = default_expiry(services, body.expires_at)
    kept = {"capture_id": capture.id, "name": body.name, "expires_at": expires_at,
            "idempotency": submit.idempotency, "resolved_run": resolved.to_json(),
            "cap": services.settings.max_active_jobs}
    services.limits.change(tenant)
    try:
        if groups:
            job, sent = services.store.create_parted(
                tenant, body.pipeline, params.model_dump(mode="json"), groups, **kept)
        else:
            job = services.store.create(tenant, body.pipeline, params.model_dump(mode="json"),
                                        **kept)
            sent = [job]
    except (NotCreated, CapReached) as exc:  # a submit with the same key won, the cap
        if (first := submit.first()) is not None:  # was reached or the capture was deleted
            return accepted(services, first, replayed=True)
        if isinstance(exc, CapReached):
            raise cap_refused(exc) from None
        raise ApiError(404, f"no capture {body.capture_id!r}") from None
    for each in sent:
        send(services, each)
    return accepted(services, job)


@router.get("", response_model=JobPage)
def list_jobs(services: ServicesDep, tenant: TenantDep, state: JobState | None = None,
              cursor: Annotated[str | None, Query(max_length=512)] = None,
              limit: Annotated[int, Query(ge=1, le=200)] = 50) -> JobPage:
    """The caller's jobs, newest first; pass next_cursor to read the next page."""
    rows, last = services.store.job_page(tenant, state, after(cursor), limit)
    return JobPage(items=[job_out(j, services) for j in rows], next_cursor=next_cursor(last))


@router.get("/{job_id}", response_model=JobOut)
def read_job(job_id: str, services: ServicesDep, tenant: TenantDep) -> JobOut:
    return job_out(get_job(services.store, job_id, tenant), services)


@router.get("/{job_id}/events", response_class=StreamingResponse,
            responses={200: {"description": "Server-sent events: state, progress, artifact",
                             "content": {"text/event-stream": {"schema": {"type": "string"}}}},
                       **error_responses(400, 429)})
def job_event_stream(job_id: str, services: ServicesDep, tenant: TenantDep,
                     last_event_id: Annotated[str | None, Header()] = None) -> StreamingResponse:
    """Progress as server-sent events; reconnect with Last-Event-ID to resume. 429 with
    Retry-After past the tenant's cap of open streams."""
    get_job(services.store, job_id, tenant)
    after = None
    if last_event_id is not None and last_event_id.strip():
        value = last_event_id.strip()
        if not (value.isascii() and value.isdigit()) or len(value) > 18:
            raise ApiError(400, f"Last-Event-ID: expected an event id, got {value[:40]!r}")
        after = int(value)
    s = services.settings
    slot = services.limits.open_stream(tenant)  # last: nothing may fail between it and
    stream = job_events(services.store, job_id, after, poll=s.sse_poll_seconds,  # its stream
                        keepalive=s.sse_keepalive_seconds)
    return HeldStream(stream, slot, media_type="text/event-stream", headers={
        "Cache-Control": "no-store", "X-Accel-Buffering": "no"})


@router.get("/{job_id}/logs", response_model=LogsOut)
def job_logs(job_id: str, services: ServicesDep, tenant: TenantDep,
             offset: Annotated[int, Query(ge=0, le=2**31 - 1)] = 0,
             limit: Annotated[int, Query(ge=1, le=10_000)] = 1000) -> LogsOut:
    """Log lines from `offset`; poll with next_offset until complete."""
    job = get_job(services.store, job_id, tenant)
    rows = services.store.logs(job.id, offset, limit + 1)
    more = len(rows) > limit
    rows = rows[:limit]
    next_offset = rows[-1].seq + 1 if rows else offset
    return LogsOut(lines=[r.line for r in rows], offset=offset, next_offset=next_offset,
                   complete=job.state in TERMINAL and not more)


@router.post("/{job_id}/cancel", status_code=202, response_model=JobOut,
             responses=error_responses(409, 429))
def cancel_job(job_id: str, services: ServicesDep, tenant: TenantDep) -> JSONResponse:
    """Cancel: a queued job at once, a running one at its next step (its worker process is
    ended if it does not stop within seconds); a job run as parts: every part likewise, none
    left queued. 409 when it has already ended; 429 past the rate of job changes."""
    job = get_job(services.store, job_id, tenant)
    if job.state in TERMINAL:
        raise ApiError(409, f"job {job_id} already {job.state}")
    services.limits.change(tenant)
    job = services.store.request_cancel(job_id, tenant)
    if job is None:
        raise ApiError(404, f"no job {job_id!r}")
    return accepted(services, job)


@router.post("/{job_id}/retry", status_code=202, response_model=JobOut,
             responses=error_responses(409, 429))
def retry_job(job_id: str, services: ServicesDep, tenant: TenantDep) -> JSONResponse:
    """Queue a failed or cancelled job again: a reconstruction resumes from its last
    checkpoint (run as parts: only its failed and cancelled parts run again, each from its
    own checkpoint), a render starts over. 429 past the rate of job changes or the
    active-jobs cap (the job counts again once queued)."""
    job = get_job(services.store, job_id, tenant)
    if job.state not in ("failed", "cancelled"):
        raise ApiError(409, f"job {job_id} is {job.state}; only failed or cancelled jobs are "
                            "retried")
    if get_pipeline(job.pipeline).source == "job" and job.source_job_id is None:
        raise ApiError(409, f"job {job_id}'s source reconstruction was deleted; it cannot run "
                            "again")
    if job.capture_id is None:
        raise ApiError(409, f"job {job_id}'s capture was deleted; it cannot run again")
    services.limits.change(tenant)
    try:
        job = services.store.retry(job_id, tenant, services.settings.max_active_jobs)
    except CapReached as exc:
        raise cap_refused(exc) from None
    if job is None:
        raise ApiError(404, f"no job {job_id!r}")
    if job.state not in ACTIVE:
        raise ApiError(409, f"job {job_id} is {job.state}; only failed or cancelled jobs are "
                            "retried")
    for each in services.store.to_dispatch(job.id):
        send(services, services.store.get(each) or job)
    return accepted(services, job)


@router.delete("/{job_id}", status_code=204, responses={204: {"description": "Deleted"},
                                                        **error_responses(409, 429)})
def delete_job(job_id: str, services: ServicesDep, tenant: TenantDep) -> Response:
    """Delete a finished job with its artifacts, logs and events (409 while queued or
    running: cancel it first; 409 while a queued or running render needs its results; 429
    past the rate of job changes)."""
    state = get_job(services.store, job_id, tenant).state  # refused here: no token taken
    if state in ACTIVE:
        raise ApiError(409, f"job {job_id} is {state}; cancel it first")
    services.limits.change(tenant)
    for each in deleted(services.store.delete_job(job_id, tenant), "job", job_id):
        services.blobs.delete_prefix(f"jobs/{each}")
        shutil.rmtree(services.settings.scratch / "jobs" / each, ignore_errors=True)
    return Response(status_code=204)
