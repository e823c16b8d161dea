"""Messages with nothing to run are dropped in the Celery parent, before they reach the pool.

Every pool process is a fresh interpreter that imports torch (seconds), and each runs one task
(worker.celery_app). A message whose job was cancelled, has ended, was deleted, waits for its
parts or runs on another live worker only finds that out in the pool process, when it claims
the job: each leftover message of a tenant's retry/cancel pairs cost a pool process, and
another tenant's small job waited behind them (3.1 s became 52.4 s with 15 pairs). The parent
asks the job store first (`JobStore.peek`, a read; the claim asks again in the same words
under its lock) and acknowledges such a message itself.

Celery's own path for a message it must not run is a revoked task: the request class answers
`revoked()`, and the worker then releases the pool slot it reserved. This class answers it for
messages with nothing to run too, after acknowledging them.
"""

from __future__ import annotations

import logging

from celery.worker.request import Request
from celery.worker.state import task_ready

from worker.settings import get_settings
from worker.store import JobStore

__all__ = ["JobRequest"]

log = logging.getLogger("dgs.worker")

_DROPPED = {
    "leased": "it is running on {job.lease_owner}",
    "terminal": "it has ended ({job.state})",
    "missing": "it was deleted",
    "waiting": "its parts are queued or running (it is assembled after them)",
}
_STORES: dict[str, JobStore] = {}


def _store() -> JobStore:
    url = get_settings().database
    if url not in _STORES:
        _STORES[url] = JobStore(url)
    return _STORES[url]


class JobRequest(Request):
    """A dgs.run_job delivery in the Celery parent (the task's `Request` class)."""

    def revoked(self) -> bool:
        if super().revoked():
            return True
        job_id = self.args[0] if self.args else None
        try:
            refused = _store().peek(str(job_id)) if job_id is not None else None
        except Exception as exc:  # the job store is away: the pool process decides
            log.warning("job %s: could not look it up in the parent (%s); sent to the pool",
                        job_id, type(exc).__name__)
            return False
        if refused is None:
            return False
        log.info("job %s: %s; its message is dropped (no pool process started)", job_id,
                 _DROPPED[refused.status].format(job=refused.job))
        task_ready(self)
        self.acknowledge()
        self._already_revoked = True
        return True
