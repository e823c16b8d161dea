"""The embedded worker that `dgs serve` supervises: restarted when it dies, and never left
behind when `dgs serve` itself dies (even by SIGKILL)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

from worker_harness import wait_for

from worker.settings import WorkerSettings
from worker.supervise import WORKER_NICE, EmbeddedWorker

SUPERVISOR = textwrap.dedent("""
    import sys, time
    from worker.settings import WorkerSettings
    from worker.supervise import EmbeddedWorker
    w = EmbeddedWorker(WorkerSettings(data_dir=sys.argv[1])).start()
    while w.proc is None:
        time.sleep(0.05)
    print(w.proc.pid, flush=True)
    time.sleep(600)
""")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()[0] != "Z"


def test_embedded_worker_is_restarted_when_it_dies(tmp_path: Path):
    w = EmbeddedWorker(WorkerSettings(data_dir=tmp_path)).start()
    try:
        first = wait_for(lambda: w.proc, 300, "the worker to start")
        wait_for(lambda: " ready." in w.log_path.read_text(errors="replace"), 300,
                 "the worker to be ready")
        # The worker yields the cores to the API it shares the machine with.
        nice = int(Path(f"/proc/{first.pid}/stat").read_text().rsplit(")", 1)[1].split()[16])
        assert nice == min(19, os.nice(0) + WORKER_NICE)
        os.killpg(first.pid, signal.SIGKILL)
        second = wait_for(lambda: w.proc if w.proc is not first else None, 300,
                          "a new worker process")
        assert second.pid != first.pid and w.restarts == 1
    finally:
        w.stop()
    assert w.proc.poll() is not None


def test_embedded_worker_dies_with_its_supervisor(tmp_path: Path):
    sup = subprocess.Popen([sys.executable, "-c", SUPERVISOR, str(tmp_path)],
                           stdout=subprocess.PIPE, text=True)
    child = int(sup.stdout.readline())
    wait_for(lambda: (tmp_path / "logs" / "worker.log").is_file()
             and " ready." in (tmp_path / "logs" / "worker.log").read_text(errors="replace"),
             300, "the worker to be ready")
    sup.kill()  # SIGKILL: no chance to stop its worker
    sup.wait()
    wait_for(lambda: not _alive(child), 300, "the orphaned worker to exit")
