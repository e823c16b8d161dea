"""Starting workers: `run_worker` (what `dgs worker` runs) and `EmbeddedWorker`, the worker
subprocess that `dgs serve` supervises when no broker is configured (docs/design.md section 4)."""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from celery import Celery
from celery.signals import worker_shutting_down
from celery.worker import state as worker_state

from worker.app import app
from worker.broker import BrokerInspector
from worker.celery_app import dispatch
from worker.db import migrate
from worker.settings import WorkerSettings, get_settings
from worker.store import JobStore
from worker.sweeper import Sweeper
from worker.watchdog import Watchdog

__all__ = ["EmbeddedWorker", "busy_pool_processes", "job_sender", "make_sweeper",
           "run_gpu_workers", "run_worker", "stop_all", "supervised", "worker_env"]

log = logging.getLogger("dgs.worker")


def make_sweeper(app: Celery, settings: WorkerSettings, **kwargs) -> Sweeper:
    """The sweeper of a process: it sends jobs with `app` and looks into its broker for the
    messages of queued jobs (worker.broker)."""
    return Sweeper(settings, job_sender(app, settings),
                   held=BrokerInspector(app, settings).held_jobs, **kwargs)


def job_sender(app: Celery, settings: WorkerSettings) -> Callable[[str], None]:
    """send(job_id): dispatch a job already in the store (its pipeline decides the limits)."""
    store = JobStore(settings.database)

    def send(job_id: str) -> None:
        job = store.get(job_id)
        if job is not None:
            dispatch(app, settings, job_id, job.pipeline)

    return send


def run_worker(*, concurrency: int = 1, loglevel: str = "INFO", hostname: str | None = None,
               sweeper: bool = True) -> int:
    """Migrate the job store, start the sweeper and watchdog threads, run the Celery worker
    (blocks)."""
    settings = get_settings()
    logging.basicConfig(level=loglevel.upper(), format="%(asctime)s %(name)s %(message)s")
    migrate(settings.database)

    if sweeper:
        _RUNNING["sweeper"] = make_sweeper(app, settings).start()
    # It outlives a warm shutdown: a stuck pool process would otherwise hold it forever.
    Watchdog(settings, busy_pool_processes).start()

    worker_shutting_down.connect(_drain, weak=False)
    # Gossip, mingle and worker heartbeats need broadcast, which the SQLite transport lacks;
    # the job store's leases do that work here.
    argv = ["worker", f"--concurrency={concurrency}", "--pool=prefork", f"--loglevel={loglevel}",
            "-Q", settings.queue, "-n", hostname or _node_name(settings),
            "--without-gossip", "--without-mingle", "--without-heartbeat"]
    app.worker_main(argv)
    return 0


def busy_pool_processes() -> dict[int, str]:
    """{pid: job id} of this Celery worker's pool processes that run a task now."""
    out: dict[int, str] = {}
    try:
        requests = list(worker_state.active_requests)
    except RuntimeError:  # changed while being read: the watchdog looks again soon
        return out
    for request in requests:
        if request.worker_pid and request.args:
            out[request.worker_pid] = str(request.args[0])
    return out


_RUNNING: dict[str, object] = {}


def _drain(sig=None, how=None, exitcode=None, **_) -> None:
    """A warm shutdown (SIGTERM to the worker) waits for running tasks; tell each task process
    to stop at its next step, checkpoint and put its job back in the queue, so the shutdown
    takes seconds and another worker resumes the job (worker.runner). This worker's sweeper
    stops first: the job must be sent by someone else, not taken back by this worker. Idle
    pool processes are left alone: the pool ends them as it closes (killed now, the pool
    would start new ones during the shutdown)."""
    sweeper = _RUNNING.pop("sweeper", None)
    if sweeper is not None:
        sweeper.stop()
    for pid in busy_pool_processes():
        try:
            os.kill(pid, signal.SIGTERM)
        except ProcessLookupError:
            pass


def _node_name(settings: WorkerSettings) -> str:
    suffix = f"-{settings.worker_name}" if settings.worker_name else ""
    return f"dgs{suffix}@{socket.gethostname()}"


def supervised(parent_pid: int, nice: int) -> bool:
    """In a worker that `EmbeddedWorker` started: receive SIGTERM when its supervisor dies,
    however it dies, so no orphaned worker keeps consuming the queue (Linux prctl
    PR_SET_PDEATHSIG; a no-op elsewhere), and add `nice` to its niceness. False when the
    supervisor is already gone. Done here, not in a preexec function between fork and exec:
    Python code in the child of a process with threads may wait forever on a lock that a
    thread held at the fork (the API's SQLite connections), as the pool processes did."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if nice:
        try:
            os.nice(nice)
        except OSError:
            pass
    return os.getppid() == parent_pid


WORKER_NICE = 5
"""Niceness added to the embedded worker: on the machine it shares with `dgs serve`, the API
keeps answering (polls, progress, downloads) while a job trains on every core."""


def worker_env(settings: WorkerSettings, index: int, count: int,
               gpu: str | None = None) -> dict[str, str]:
    """The variables of worker `index` of `count` on one machine: its own Celery node name,
    and its share of the cores (`torch_threads`, OMP_NUM_THREADS: the cores divided by
    `count`, unless the settings fix it), so `count` workers do not oversubscribe them; with
    `gpu`, the one GPU it sees (CUDA_VISIBLE_DEVICES, so its `cuda:0` is that GPU)."""
    threads = settings.torch_threads or max(1, (os.cpu_count() or 1) // count)
    name = f"gpu{gpu}" if gpu is not None else f"w{index + 1}"
    env = {"DGS_TORCH_THREADS": str(threads), "OMP_NUM_THREADS": str(threads)}
    if count > 1 or gpu is not None:
        prefix = f"{settings.worker_name}-" if settings.worker_name else ""
        env["DGS_WORKER_NAME"] = prefix + name
    if gpu is not None:
        env["CUDA_VISIBLE_DEVICES"] = gpu
    return env


class EmbeddedWorker:
    """Keeps one `dgs worker` subprocess running (restarted with back-off if it dies), with
    `settings` (as DGS_* variables, over this process's environment, then `env`); its output
    goes to <data_dir>/logs/<log_name>. `nice` is added to its niceness (the embedded worker
    shares its machine with the API)."""

    def __init__(self, settings: WorkerSettings, env: dict[str, str] | None = None, *,
                 log_name: str = "worker.log", nice: int = WORKER_NICE,
                 args: list[str] | None = None):
        self.settings, self.log_name, self.nice = settings, log_name, nice
        self.args = list(args or [])
        """Extra arguments of its `dgs worker`."""
        self.env = {**os.environ, **settings.to_env(), **(env or {})}
        self.proc: subprocess.Popen | None = None
        self.restarts = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="dgs-embedded-worker",
                                        daemon=True)

    @property
    def log_path(self) -> Path:
        return self.settings.data_dir / "logs" / self.log_name

    def start(self) -> EmbeddedWorker:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._thread.start()
        return self

    def _spawn(self) -> subprocess.Popen:
        out = open(self.log_path, "ab")
        try:
            return subprocess.Popen([sys.executable, "-m", "core.cli", "worker",
                                     f"--parent-pid={os.getpid()}", f"--nice={self.nice}",
                                     *self.args],
                                    env=self.env, stdout=out, stderr=subprocess.STDOUT,
                                    start_new_session=True)
        finally:
            out.close()

    def _loop(self) -> None:
        delay = 1.0
        while not self._stop.is_set():
            started = time.monotonic()
            self.proc = self._spawn()
            code = self.proc.wait()
            if self._stop.is_set():
                return
            self.restarts += 1
            if time.monotonic() - started > 60:
                delay = 1.0
            log.warning("embedded worker exited with %s; restarting in %.0f s (see %s)", code,
                        delay, self.log_path)
            if self._stop.wait(delay):
                return
            delay = min(delay * 2, 30.0)

    def stop(self, grace: float = 10.0) -> None:
        """Warm shutdown (the running job stops at its next checkpoint or is resumed later),
        then a kill after `grace` seconds."""
        self._stop.set()
        proc = self.proc
        if proc is None or proc.poll() is not None:
            return
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=grace)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        except ProcessLookupError:
            pass
        self._thread.join(timeout=5)


def run_gpu_workers(gpus: list[str], args: list[str]) -> int:
    """`dgs worker --gpus 0,1,...`: one supervised `dgs worker` per GPU, each seeing only its
    GPU and its share of the cores (`worker_env`), logs in <data_dir>/logs/worker-gpu<N>.log;
    runs until SIGTERM or SIGINT, then shuts each down warmly (their jobs go back to the
    queue)."""
    settings = get_settings()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    migrate(settings.database)
    workers = [EmbeddedWorker(settings, worker_env(settings, i, len(gpus), gpu),
                              log_name=f"worker-gpu{gpu}.log", nice=0, args=args).start()
               for i, gpu in enumerate(gpus)]
    done = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: done.set())
    log.info("%d workers, one per GPU (%s); logs in %s", len(gpus), ", ".join(gpus),
             settings.data_dir / "logs")
    done.wait()
    stop_all(workers, grace=60.0)
    return 0


def stop_all(workers: list[EmbeddedWorker], grace: float = 10.0) -> None:
    """Stop every worker at once (each gets `grace` seconds for its warm shutdown)."""
    threads = [threading.Thread(target=w.stop, args=(grace,)) for w in workers]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
