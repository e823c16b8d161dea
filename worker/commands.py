"""`dgs worker`: a Celery worker for this deployment's queue (concurrency 1, prefork, one task
per child process), with the job store migrated first and a sweeper thread that re-sends jobs
whose worker was lost."""

from __future__ import annotations

import argparse
import sys

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("worker", help="run a worker (Celery) for the configured broker")
    p.add_argument("--concurrency", type=int, default=1,
                   help="jobs at once (default 1: one GPU, or the CPU, per worker)")
    p.add_argument("--loglevel", default="INFO")
    p.add_argument("--hostname", default=None, help="Celery node name (default dgs@<host>)")
    p.add_argument("--no-sweeper", action="store_true",
                   help="do not re-send jobs of lost workers from this process")
    p.add_argument("--gpus", default=None, metavar="0,1,...",
                   help="one worker per GPU on this machine (each sees only its GPU and its "
                        "share of the cores; logs in <data_dir>/logs/worker-gpu<N>.log)")
    # Set by a supervisor (`dgs serve`, `dgs worker --gpus`) for the worker it starts.
    p.add_argument("--parent-pid", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--nice", type=int, default=0, help=argparse.SUPPRESS)
    p.set_defaults(func=_worker)


def _worker(args: argparse.Namespace) -> int:
    # lazy: `dgs` starts without the worker extra installed
    from pydantic import ValidationError
    # lazy: as above
    from worker.settings import describe, get_settings

    try:  # before anything that reads the settings (worker.app reads them at import)
        get_settings()
    except ValidationError as exc:
        print(f"dgs worker: {describe(exc)}", file=sys.stderr)
        return 2
    # lazy: after the settings are known good
    from worker.supervise import run_gpu_workers, run_worker, supervised

    if args.parent_pid is not None and not supervised(args.parent_pid, args.nice):
        print(f"dgs worker: its supervisor (pid {args.parent_pid}) is gone", file=sys.stderr)
        return 1
    if args.gpus is not None:
        gpus = [g.strip() for g in args.gpus.split(",") if g.strip()]
        if not gpus or not all(g.isdigit() for g in gpus):
            print(f"dgs worker: --gpus: expected GPU indices such as 0,1; got {args.gpus!r}",
                  file=sys.stderr)
            return 2
        extra = [f"--loglevel={args.loglevel}"] + (["--no-sweeper"] if args.no_sweeper else [])
        return run_gpu_workers(gpus, extra)

    return run_worker(concurrency=args.concurrency, loglevel=args.loglevel,
                      hostname=args.hostname, sweeper=not args.no_sweeper)
