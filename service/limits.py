"""One tenant cannot starve the others (issue 42; docs/design.md 3.5): what the API refuses with
429 and a Retry-After.

- **State changes** (submits, cancel, retry, delete) take a token from the tenant's bucket in
  the job store (`worker.quota.take`): `DGS_JOB_CHANGES_BURST` at once, then
  `DGS_JOB_CHANGES_PER_MINUTE`; shared by every API process of the deployment.
- **Active jobs**: a submit or retry past `DGS_MAX_ACTIVE_JOBS` queued or running jobs of the
  tenant (counted by the job store in the transaction that adds the job).
- **Event streams**: at most `DGS_MAX_EVENT_STREAMS` open at once per tenant on each API
  process (a stream lives in one process; N processes allow N times as many). A slot is
  freed when the stream ends, also when the client goes away: `HeldStream` listens for the
  disconnect instead of waiting for its next write to fail. Openings take a token from the
  tenant's bucket in this process (`DGS_MAX_EVENT_STREAMS` at once, then
  `DGS_EVENT_STREAMS_PER_MINUTE`): a client that opens and drops streams as fast as it can
  (a stream of an ended job ends at once) would otherwise read the job store with every one.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import anyio
from fastapi.responses import StreamingResponse
from starlette.types import Receive, Scope, Send

from service.errors import ApiError
from service.settings import ServiceSettings
from worker.quota import CapReached, Rate, peek, take
from worker.store import JobStore

__all__ = ["CAP_RETRY_AFTER_SECONDS", "STREAM_RETRY_AFTER_SECONDS", "HeldStream", "Limits",
           "StreamSlot", "cap_refused"]

CAP_RETRY_AFTER_SECONDS = 30
"""Retry-After of a submit past the active-jobs cap: a slot frees when a job ends, which the
API cannot foresee; half a minute keeps a waiting client's polls cheap."""
STREAM_RETRY_AFTER_SECONDS = 10
"""Retry-After of an event stream past the cap (follow the job by polling meanwhile)."""


def too_fast(wait: float, what: str, burst: int, per_minute: float, which: str, meanwhile: str,
             *, code: str) -> ApiError:
    """The 429 of a request past a rate (`burst` at once, then `per_minute`), `wait` seconds
    before the bucket has a token again."""
    retry_after = max(1, math.ceil(wait))
    return ApiError(
        429, f"too many {what}: {burst} at once, then {per_minute:g} a minute {which}; try "
             f"again in {retry_after} s{meanwhile}", code=code, retryable=True,
        headers={"Retry-After": str(retry_after)})


def cap_refused(exc: CapReached) -> ApiError:
    """The 429 of a submit or retry past the active-jobs cap."""
    return ApiError(
        429, f"too many active jobs: {exc.active} of yours are queued or running and the cap "
             f"is {exc.cap} (DGS_MAX_ACTIVE_JOBS); submit again when one has ended",
        code="too_many_jobs", retryable=True,
        details=[{"path": "jobs", "message": f"{exc.active} active, cap {exc.cap}"}],
        headers={"Retry-After": str(CAP_RETRY_AFTER_SECONDS)})


class StreamSlot:
    """One open event stream of a tenant; `release()` (idempotent) gives the slot back."""

    def __init__(self, limits: Limits, tenant: str):
        self._limits, self.tenant, self._held = limits, tenant, True

    def release(self) -> None:
        with self._limits.lock:
            if self._held:
                self._held = False
                left = self._limits.streams[self.tenant] - 1
                if left:
                    self._limits.streams[self.tenant] = left
                else:
                    del self._limits.streams[self.tenant]


class Limits:
    """The process's limits on `settings` and the job store `store`; `clock` (seconds since
    the epoch) is what the rate limit counts time with (tests drive it)."""

    def __init__(self, settings: ServiceSettings, store: JobStore,
                 clock: Callable[[], float] = time.time):
        self.settings, self.store, self.clock = settings, store, clock
        self.changes = Rate(settings.job_changes_per_minute / 60.0, settings.job_changes_burst)
        self.openings = Rate(settings.event_streams_per_minute / 60.0,
                             settings.max_event_streams)
        self.lock = threading.Lock()
        self.streams: dict[str, int] = {}
        """Open event streams of this process, by tenant."""
        self.opened: dict[str, tuple[float, float]] = {}
        """The bucket of stream openings of this process, by tenant: (tokens, stamp)."""

    def change(self, tenant: str) -> None:
        """Count one state change of `tenant` (a submit, cancel, retry or delete); 429
        rate_limited with Retry-After when its bucket is empty."""
        self._refuse_change(take(self.store.url, f"changes:{tenant}", self.changes,
                                 self.clock()))

    def admit(self, tenant: str) -> None:
        """Before a submit is checked (its parameters, its capture: reads of the artifact
        store), the cheap refusals: 429 when the tenant's bucket is empty or its active jobs
        are at the cap, taking nothing (the job store decides again when the job is added)."""
        self._refuse_change(peek(self.store.url, f"changes:{tenant}", self.changes,
                                 self.clock()))
        with self.store.session(write=False) as s:
            active = JobStore.active_jobs(s, tenant)
        if active >= self.settings.max_active_jobs:
            raise cap_refused(CapReached(active, self.settings.max_active_jobs))

    def _refuse_change(self, wait: float) -> None:
        if wait:
            s = self.settings
            raise too_fast(wait, "job changes", s.job_changes_burst, s.job_changes_per_minute,
                           "(submits, cancels, retries and deletes together)", "",
                           code="rate_limited")

    def open_stream(self, tenant: str) -> StreamSlot:
        """A slot for one more event stream of `tenant`; 429 too_many_streams past the cap on
        open streams or past the rate of openings."""
        cap, now = self.settings.max_event_streams, self.clock()
        with self.lock:
            open_now = self.streams.get(tenant, 0)
            if open_now >= cap:
                raise ApiError(
                    429, f"too many event streams: {open_now} of yours are open and the cap "
                         f"is {cap} (DGS_MAX_EVENT_STREAMS); close one, or poll "
                         "GET /v1/jobs/{id} meanwhile", code="too_many_streams",
                    retryable=True, headers={"Retry-After": str(STREAM_RETRY_AFTER_SECONDS)})
            tokens, stamp = self.opened.get(tenant, (float(cap), now))
            wait, tokens, stamp = self.openings.take(tokens, stamp, now)
            if wait:
                raise too_fast(wait, "event streams opened", cap,
                               self.settings.event_streams_per_minute,
                               "(DGS_EVENT_STREAMS_PER_MINUTE)",
                               ", or poll GET /v1/jobs/{id} meanwhile", code="too_many_streams")
            self.opened[tenant] = (tokens, stamp)
            self.streams[tenant] = open_now + 1
        return StreamSlot(self, tenant)


class HeldStream(StreamingResponse):
    """A streaming response that holds a `StreamSlot` until it ends: its body is sent while
    the client's disconnect is awaited beside it, and whichever comes first ends both.
    Starlette does so itself only under servers of ASGI spec below 2.4 (uvicorn 0.54 says
    2.3); under 2.4 it learns of a disconnect when a write fails, and an idle event stream
    writes once in `sse_keepalive_seconds`, so a slot would stay taken that long."""

    def __init__(self, content, slot: StreamSlot, **kw):
        super().__init__(content, **kw)
        self.slot = slot

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            async with anyio.create_task_group() as group:

                async def body() -> None:
                    try:
                        await self.stream_response(send)
                    except OSError:  # the client went away mid-write
                        pass
                    group.cancel_scope.cancel()

                group.start_soon(body)
                await self.listen_for_disconnect(receive)
                group.cancel_scope.cancel()
        finally:
            self.slot.release()
