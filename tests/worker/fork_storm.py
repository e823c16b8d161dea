"""Reproduction of the pool child that hung after a fork (issue 42): start `--children` pool
processes from a thread of their own, as billiard's supervisor thread does, while the main
thread and a second thread (the broker's poll, the sweeper) hammer SQLite through the job
store's engine; every child collects garbage (freeing whatever SQLite handle it inherited) and
runs a query of its own. A child that has not exited within `--wait` seconds is counted as hung
and killed. Prints one JSON line: {"start", "children", "hung", "seconds"}.

    python tests/worker/fork_storm.py DB_PATH --start fork --children 300

`--start` defaults to the start method of the worker's pool (worker.celery_app). Kept light
at the top: a spawned child imports this file again before it runs `_child`.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import signal
import sqlite3
import sys
import threading
import time
from pathlib import Path


def _child(db: str) -> None:
    """A pool process's first moments: garbage collection (torch's import allocates enough
    to start one) and a query of its own."""
    gc.collect()
    with sqlite3.connect(db, timeout=30) as conn:
        conn.execute("SELECT count(*) FROM t").fetchone()


def _hammer(url: str, db: str, stop: threading.Event) -> None:
    """What the Celery parent's threads do: queries through the job store's engine (pooled
    connections, which the worker's at-fork hook hands to the child) and connections opened
    and dropped (the broker's transport)."""
    while not stop.is_set():
        _hammer_once(url, db)


def _fork_all(ctx, db: str, children: int, batch: int, wait: float, out: dict) -> None:
    """Start the children `batch` at a time from this (non-main) thread; count those that
    have not exited within `wait` seconds of their batch's start."""
    for first in range(0, children, batch):
        procs = [ctx.Process(target=_child, args=(db,)) for _ in range(min(batch,
                                                                           children - first))]
        try:
            for p in procs:
                p.start()
            deadline = time.monotonic() + wait
            for p in procs:
                p.join(max(0.0, deadline - time.monotonic()))
                if p.is_alive():
                    out["hung"] += 1
                elif p.exitcode != 0:
                    out["failed"] += 1
        finally:  # a hung child never outlives the run, whatever ended it
            for p in procs:
                if p.pid is not None and p.is_alive():
                    os.kill(p.pid, signal.SIGKILL)
                    p.join()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("db", type=Path)
    ap.add_argument("--start", default=None, help="fork or spawn (default: the worker's)")
    ap.add_argument("--children", type=int, default=200)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--wait", type=float, default=20.0,
                    help="seconds a batch of children has to exit")
    args = ap.parse_args(argv)
    import billiard

    if args.start is None:
        from worker.celery_app import make_celery
        from worker.settings import WorkerSettings

        args.start = make_celery(WorkerSettings(data_dir=args.db.parent)).conf.\
            worker_pool_start_method
    db = str(args.db)
    with sqlite3.connect(db) as conn:
        conn.execute("CREATE TABLE IF NOT EXISTS t (x INTEGER)")
        conn.executemany("INSERT INTO t VALUES (?)", [(i,) for i in range(2000)])
    url = f"sqlite:///{db}"
    stop = threading.Event()
    out = {"start": args.start, "children": args.children, "hung": 0, "failed": 0}
    threading.Thread(target=_hammer, args=(url, db, stop), daemon=True).start()
    forker = threading.Thread(target=_fork_all, daemon=True, args=(
        billiard.get_context(args.start), db, args.children, args.batch, args.wait, out))
    t0 = time.monotonic()
    forker.start()
    while forker.is_alive():  # the main thread polls, as Celery's consumer polls the broker
        _hammer_once(url, db)
    out["seconds"] = round(time.monotonic() - t0, 1)
    stop.set()
    print(json.dumps(out), flush=True)
    return 0


def _hammer_once(url: str, db: str) -> None:
    from sqlalchemy import text

    from worker.db import engine_for

    try:
        with engine_for(url).connect() as c:
            c.execute(text("SELECT count(*) FROM t")).scalar()
        conn = sqlite3.connect(db, timeout=30)
        conn.execute("SELECT group_concat(x) FROM (SELECT x FROM t ORDER BY random())"
                     ).fetchone()
        del conn
    except Exception:  # noqa: BLE001  (busy: the load is the point, not each query)
        pass


if __name__ == "__main__":
    sys.exit(main())
