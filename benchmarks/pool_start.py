"""What a pool process's start costs a job (issue 42): a real worker (embedded default: SQLite
job store and broker) is sent `--jobs` jobs at once, each of which a pool process claims and
fails at once (its capture is gone), so each job costs one pool process, its imports (torch
among them) and one claim; then, with the worker idle, one more job, whose pool process was
started before it arrived.

    python benchmarks/pool_start.py [--start fork|spawn] [--jobs 8] [--dead 15]

Prints one JSON line: the start method, seconds per job back to back (first claim to last
end, over jobs - 1), the idle job's seconds from dispatch to claim and to its end, and then
the seconds to the end of a job sent behind `--dead` messages of cancelled jobs (a tenant's
retry/cancel pairs leave one each).
`--start` overrides the worker's own start method (worker.celery_app) through Celery's
--pool-start-method, to measure the one it replaced.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from polling import wait_until  # noqa: E402  (beside this script)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--start", choices=("fork", "spawn"), default=None)
    ap.add_argument("--jobs", type=int, default=8)
    ap.add_argument("--dead", type=int, default=15,
                    help="messages of cancelled jobs sent before the last job")
    args = ap.parse_args()
    data = Path(tempfile.mkdtemp(prefix="dgs-pool-start-"))
    os.environ.update({"DGS_DATA_DIR": str(data), "OMP_NUM_THREADS": "1"})
    from worker.celery_app import dispatch, make_celery
    from worker.db import migrate
    from worker.settings import WorkerSettings
    from worker.store import JobStore

    settings = WorkerSettings()
    migrate(settings.database)
    store, celery = JobStore(settings.database), make_celery(settings)
    extra = ["--pool-start-method", args.start] if args.start else []
    log = open(data / "worker.log", "wb")
    worker = subprocess.Popen([sys.executable, "-m", "celery", "-A", "worker.app", "worker",
                               "--concurrency=1", "-Q", settings.queue, "--without-gossip",
                               "--without-mingle", "--without-heartbeat", "--loglevel=INFO",
                               *extra], cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                              start_new_session=True)
    try:
        wait_until(lambda: b" ready." in (data / "worker.log").read_bytes(), 300, "the worker",
                   every=0.05)

        def submit() -> str:
            job = store.create("t1", "reconstruct", {"preset": "test"}, capture_id=None)
            dispatch(celery, settings, job.id, "reconstruct")
            return job.id

        def ended(job_id: str):
            job = store.get(job_id)
            return job if job.state in ("succeeded", "failed", "cancelled") else None

        ids = [submit() for _ in range(args.jobs)]
        jobs = [wait_until(lambda i=i: ended(i), 600, f"job {i}", every=0.05) for i in ids]
        first = min(j.started_at for j in jobs)
        last = max(j.finished_at for j in jobs)
        time.sleep(5)  # the next pool process is started and idle before the last job comes
        t0 = time.time()
        idle = submit()
        claimed = wait_until(lambda: store.get(idle).started_at, 300, "the idle job's claim",
                             every=0.05)
        done = wait_until(lambda: ended(idle), 300, "the idle job", every=0.05)
        time.sleep(5)
        for _ in range(args.dead):  # a retry sends a message, the cancel leaves it behind
            job = store.create("t1", "reconstruct", {"preset": "test"}, capture_id=None)
            store.request_cancel(job.id, "t1")
            dispatch(celery, settings, job.id, "reconstruct")
        t1 = time.time()
        last_job = submit()
        behind = wait_until(lambda: ended(last_job), 900, "the job behind the dead messages",
                            every=0.05)
        print(json.dumps({
            "start": args.start or celery.conf.worker_pool_start_method, "jobs": args.jobs,
            "states": sorted({j.state for j in jobs}),
            "seconds_per_job": round((last - first).total_seconds() / (args.jobs - 1), 2),
            "idle_to_claim_s": round(claimed.timestamp() - t0, 2),
            "idle_to_end_s": round(done.finished_at.timestamp() - t0, 2),
            "dead": args.dead,
            "behind_dead_to_end_s": round(behind.finished_at.timestamp() - t1, 2)}), flush=True)
    finally:
        os.killpg(worker.pid, signal.SIGKILL)
        worker.wait()
        shutil.rmtree(data, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
