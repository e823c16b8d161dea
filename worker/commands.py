"""`dgs worker`: a Celery worker for this deployment's queue (concurrency 1, prefork, one task
per child process), with the job store migrated first and a sweeper thread that re-sends jobs
whose worker was lost."""

from __future__ import annotations

import argparse

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("worker", help="run a worker (Celery) for the configured broker")
    p.add_argument("--concurrency", type=int, default=1,
                   help="jobs at once (default 1: one GPU, or the CPU, per worker)")
    p.add_argument("--loglevel", default="INFO")
    p.add_argument("--hostname", default=None, help="Celery node name (default dgs@<host>)")
    p.add_argument("--no-sweeper", action="store_true",
                   help="do not re-send jobs of lost workers from this process")
    p.set_defaults(func=_worker)


def _worker(args: argparse.Namespace) -> int:
    # lazy: `dgs` starts without the worker extra installed
    from worker.supervise import run_worker

    return run_worker(concurrency=args.concurrency, loglevel=args.loglevel,
                      hostname=args.hostname, sweeper=not args.no_sweeper)
