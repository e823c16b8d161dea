"""A job's progress as server-sent events (text/event-stream).

Each event is a JobEvent row: `id:` its id, `event:` its kind (state, progress, artifact, and
for a job run as parts `part`: {"part": index, "event": state or progress, ...} whenever a
part changes, each batch of them followed by the job's overall progress), `data:` JSON. A new stream starts with the job's current state (an event with the id of the
latest row, so a reconnect resumes after it); a reconnect with Last-Event-ID gets every event
after that id and nothing twice. The stream polls the job store, sends a comment when idle so
proxies keep it open, and ends after the event that reports a terminal state.
"""

from __future__ import annotations

import json
import time
from collections.abc import AsyncIterator
from typing import Any

import anyio
from sqlalchemy import func, select
from starlette.concurrency import run_in_threadpool as run

from worker.models import Job, JobEvent
from worker.parts import overall_progress
from worker.store import TERMINAL, JobStore, progress_of

__all__ = ["format_event", "job_events", "snapshot"]


def format_event(event_id: int | None, kind: str, data: dict[str, Any]) -> str:
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}event: {kind}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


def snapshot(store: JobStore, job_id: str) -> tuple[int, Job | None]:
    """(id of the job's latest event, the job) read in one transaction."""
    with store.session(write=False) as s:
        last = s.scalar(select(func.max(JobEvent.id)).where(JobEvent.job_id == job_id))
        job = s.get(Job, job_id)
    return int(last or 0), job


def _state(job: Job) -> dict[str, Any]:
    return {"state": job.state, "error": job.error, "attempts": job.attempts,
            "cancel_requested": job.cancel_requested, **progress_of(job)}


async def job_events(store: JobStore, job_id: str, last_id: int | None, *, poll: float,
                     keepalive: float) -> AsyncIterator[str]:
    """The stream's text, event by event (see the module docstring)."""
    if last_id is None:
        last_id, job = await run(snapshot, store, job_id)
        if job is None:
            return
        yield format_event(last_id, "state", _state(job))
        if job.state in TERMINAL:
            return
    quiet_since = time.monotonic()
    while True:
        # The state first, then the events: a terminal state's own event is then visible too.
        job = await run(store.get, job_id)
        events = await run(store.events_after, job_id, last_id)
        for event in events:
            last_id = event.id
            yield format_event(event.id, event.kind, event.data)
            if event.kind == "state" and event.data.get("state") in TERMINAL:
                return
        if job is not None and job.parts and any(e.kind == "part" for e in events):
            # What the parts did, as the job's own progress (under the last part event's id:
            # a reconnect after it misses nothing).
            overall = overall_progress(job, await run(store.parts, job_id))
            if overall:
                yield format_event(last_id, "progress", {**progress_of(job), **overall})
        if job is None or (job.state in TERMINAL and not events):
            return
        if events:
            quiet_since = time.monotonic()
        elif time.monotonic() - quiet_since >= keepalive:
            quiet_since = time.monotonic()
            yield ": keep-alive\n\n"
        await anyio.sleep(poll)
