"""The Celery parent's look at a message before a pool process starts: one with nothing to run
is dropped, one whose tenant has not the turn is deferred.

Every pool process is a fresh interpreter that imports torch (seconds), and each runs one task
(worker.celery_app). A message whose job was cancelled, has ended, was deleted, waits for its
parts or runs on another live worker only finds that out in the pool process, when it claims
the job: each leftover message of a tenant's retry/cancel pairs cost a pool process, and
another tenant's small job waited behind them (3.1 s became 52.4 s with 15 pairs). The parent
asks the job store first (`JobStore.peek`, a read; the claim asks again in the same words
under its lock) and acknowledges such a message itself.

A message with a job to run is then picked fairly (`worker.fair`, `JobStore.pick`): when
another tenant has the turn, the message goes back to the end of the queue (rejected with
requeue: no pool process, no attempt counted) and the worker takes the next. A message that
comes round to this process again before any pick here has seen the whole queue without the
tenant whose turn it is (its message is in flight elsewhere, or lost until a sweeper sends it
again): it runs, so a worker never circles the queue for longer than one round.

Celery's own path for a message it must not run is a revoked task: the request class answers
`revoked()`, and the worker then releases the pool slot it reserved. This class answers it for
messages with nothing to run and for deferred ones, after acknowledging or requeueing them.
"""

from __future__ import annotations

import logging

from celery.worker.request import Request
from celery.worker.state import task_ready

from worker.settings import get_settings
from worker.store import Claim, JobStore

__all__ = ["JobRequest", "nothing_to_run"]

log = logging.getLogger("dgs.worker")

_DROPPED = {
    "leased": "it is running on {job.lease_owner}",
    "terminal": "it has ended ({job.state})",
    "missing": "it was deleted",
    "waiting": "its parts are queued or running (it is assembled after them)",
}
_NOTES = {
    "leased": "it is running on {job.lease_owner} (lease renewed, {left:.0f} s left); this "
              "duplicate message is dropped",
    "terminal": "it has ended ({job.state}); this duplicate message is dropped",
    "missing": "it was deleted; its message is dropped",
    "exhausted": "its worker was lost {job.redeliveries} times; it failed (worker_lost)",
    "waiting": "its parts are queued or running (it is assembled after them); this message "
               "is dropped",
}
_STORES: dict[str, JobStore] = {}
_DEFERRED: set[str] = set()
"""Ids of the messages this process deferred since its last pick."""


def _store() -> JobStore:
    url = get_settings().database
    if url not in _STORES:
        _STORES[url] = JobStore(url)
    return _STORES[url]


def nothing_to_run(claim: Claim) -> str:
    """Why a pool process's message found nothing to run (a claim or peek that refused), for
    the worker's log."""
    return _NOTES[claim.status].format(job=claim.job, left=claim.retry_in)


class JobRequest(Request):
    """A dgs.run_job delivery in the Celery parent (the task's `Request` class)."""

    def revoked(self) -> bool:
        if super().revoked():
            return True
        job_id = str(self.args[0]) if self.args else None
        if job_id is None:
            return False
        try:
            refused = _store().peek(job_id)
            pick = None if refused else _store().pick(
                job_id, get_settings().stall_seconds, force=self.id in _DEFERRED)
        except Exception as exc:  # the job store is away: the pool process decides
            log.warning("job %s: could not look it up in the parent (%s); sent to the pool",
                        job_id, type(exc).__name__)
            return False
        if refused is not None:
            log.info("job %s: %s; its message is dropped (no pool process started)", job_id,
                     _DROPPED[refused.status].format(job=refused.job))
            task_ready(self)
            self.acknowledge()
        elif pick.status == "defer":
            log.info("job %s: deferred, back to the end of the queue: tenant %s has the turn "
                     "(%d on a worker; job %s waiting)", job_id, pick.first.tenant,
                     pick.first.on_worker, pick.first.job)
            _DEFERRED.add(self.id)
            task_ready(self)
            self.reject(requeue=True)
        else:
            _DEFERRED.clear()
            return False
        self._already_revoked = True
        return True
