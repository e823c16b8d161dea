"""`dgs serve` as a fresh machine runs it: nothing configured, SQLite job store and broker in a
data folder, an embedded worker subprocess that stops with the server."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from live_server import wait_for

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.timeout(300)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _workers_of(data_dir: Path) -> list[int]:
    """Pids of `dgs worker` processes whose DGS_DATA_DIR is `data_dir`."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().split(b"\0")
            env = (entry / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"worker" in cmd and f"DGS_DATA_DIR={data_dir}".encode() in env:
            out.append(int(entry.name))
    return out


def test_serve_runs_the_api_and_an_embedded_worker(tmp_path):
    data, port = tmp_path / "data", _free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("DGS_")}
    env.update({"OMP_NUM_THREADS": "1", "DGS_QUEUE": f"serve-{port}"})
    proc = subprocess.Popen([sys.executable, "-m", "core.cli", "serve", "--port", str(port),
                             "--data-dir", str(data)], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        def ready():
            try:
                return httpx.get(f"http://127.0.0.1:{port}/readyz").status_code == 200
            except httpx.TransportError:
                assert proc.poll() is None, proc.stdout.read()
                return False

        wait_for(ready, 60, "the API")
        info = httpx.get(f"http://127.0.0.1:{port}/v1/info").json()
        assert info["tenant"] == "local" and info["keys_required"] is False
        assert (data / "dgs.sqlite3").is_file()
        log = data / "logs" / "worker.log"
        wait_for(lambda: log.is_file() and " ready." in log.read_text(errors="replace"), 120,
              "the embedded worker")
        workers = _workers_of(data)
        assert workers, "no embedded worker process"
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert f"http://127.0.0.1:{port}" in out and str(data) in out and "tenant 'local'" in out
    wait_for(lambda: not _workers_of(data), 30, "the worker to stop with the server")
