"""Helpers of the worker tests: a tiny reconstruction config, putting a capture in the store,
real `dgs worker` processes, polling."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from live_server import wait_for  # noqa: F401  (the harness's callers take it from here)

from worker.models import Capture
from worker.store import JobStore

ROOT = Path(__file__).resolve().parents[2]


def tiny_config(iterations: int = 100) -> dict:
    """Overrides for a tiny reconstruction: every stage, densification, a reset and the AO bake,
    scaled to `iterations` steps."""
    f = iterations / 100
    s = {"stage2_start": 30, "stage3_start": 70, "densify_from": 5, "densify_until": 60,
         "densify_interval": 10, "reset_interval": 40, "sh_interval": 10}
    schedule = {"iterations": iterations, **{k: max(1, round(v * f)) for k, v in s.items()}}
    return {"train": {"schedule": schedule, "init_points": 500}}


def add_capture(store: JobStore, blobs, capture: Path, capture_id: str = "cap_tiny",
                tenant: str = "t1") -> str:
    """Put a capture folder into the artifact store as the API's commit does, and its row."""
    for path in sorted(p for p in capture.rglob("*") if p.is_file()):
        blobs.put_file(f"captures/{capture_id}/{path.relative_to(capture).as_posix()}", path)
    with store.session() as s:
        s.add(Capture(id=capture_id, tenant=tenant, format="canonical", state="ready"))
    return capture_id


class WorkerProcess:
    """A real `dgs worker` (Celery, prefork, one task per child) with its own environment."""

    def __init__(self, env: dict[str, str], log: Path, args: tuple[str, ...] = ()):
        self.env, self.log, self.args = env, log, args
        self.proc: subprocess.Popen | None = None

    def start(self, timeout: float = 300.0) -> WorkerProcess:
        start = self.log.stat().st_size if self.log.exists() else 0
        with open(self.log, "ab") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "core.cli", "worker",
                                          *self.args], cwd=ROOT,
                                         env=self.env, stdout=out, stderr=subprocess.STDOUT,
                                         start_new_session=True)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            text = self.log.read_bytes()[start:].decode(errors="replace")
            if " ready." in text:
                return self
            if self.proc.poll() is not None:
                raise RuntimeError(f"worker exited with {self.proc.returncode}:\n{text[-3000:]}")
            time.sleep(0.2)
        raise RuntimeError(f"worker not ready after {timeout} s:\n{self.log.read_text()[-3000:]}")

    def kill_all(self) -> None:
        """SIGKILL the worker and its children (a machine lost)."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()

    def stop(self) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        os.killpg(self.proc.pid, signal.SIGTERM)
        try:
            self.proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            self.kill_all()


