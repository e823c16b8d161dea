"""A real `dgs serve` (API + embedded worker, SQLite, local files) on a free loopback port with
its own data folder, for the browser and documentation tests."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest

ROOT = Path(__file__).resolve().parents[1]


def wait_for(condition: Callable[[], object], timeout: float, what: str, every: float = 0.2):
    """Poll `condition` until it returns something truthy; fail naming `what`."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(every)
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def clean_env(data_dir: Path, **extra: str) -> dict[str, str]:
    """The environment of a `dgs` process on `data_dir`: the developer's DGS_* left out."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("DGS_")}
    # PATH stays as it is: the native build cache is keyed to the ninja on PATH (a different
    # ninja rebuilds the extension from scratch), so the server's worker uses the test's.
    env.update({"DGS_DATA_DIR": str(data_dir), "OMP_NUM_THREADS": "1"})
    env.update(extra)
    return env


def create_key(data_dir: Path, tenant: str = "web") -> str:
    """A new API key (`dgs keys create`)."""
    out = subprocess.run([sys.executable, "-m", "core.cli", "keys", "create", "--tenant", tenant],
                         cwd=ROOT, env=clean_env(data_dir), capture_output=True, text=True,
                         timeout=120, check=True)
    return out.stdout.strip().splitlines()[-1]


class LiveServer:
    """`dgs serve --port P` on `data_dir` until stop(); `url` once started."""

    def __init__(self, data_dir: Path, log: Path, *args: str, **env: str):
        self.data_dir, self.log_path, self.args = data_dir, log, args
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = clean_env(data_dir, DGS_QUEUE=f"live-{self.port}", **env)
        self.proc: subprocess.Popen | None = None

    def start(self, timeout: float = 120.0) -> LiveServer:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "core.cli", "serve", "--port", str(self.port),
                 *self.args],
                cwd=ROOT, env=self.env, stdout=out, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, f"dgs serve exited:\n{self.log()}"
            try:
                if httpx.get(f"{self.url}/readyz", timeout=5).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.3)
        raise AssertionError(f"dgs serve did not become ready:\n{self.log()}")

    def wait_worker(self, timeout: float = 120.0, name: str = "worker.log") -> None:
        """Until the embedded worker has connected (jobs would otherwise just wait queued);
        `name`: its log (worker-2.log, ... for the others of `dgs serve --workers N`)."""
        log = self.data_dir / "logs" / name
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if log.is_file() and " ready." in log.read_text(errors="replace"):
                return
            time.sleep(0.3)
        raise AssertionError(f"the embedded worker did not start:\n{self.log()}")

    def log(self) -> str:
        text = self.log_path.read_text(errors="replace") if self.log_path.exists() else ""
        worker = self.data_dir / "logs" / "worker.log"
        if worker.exists():
            text += "\n--- worker.log ---\n" + worker.read_text(errors="replace")[-6000:]
        return text[-12000:]

    def stop(self) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)
