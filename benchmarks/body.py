"""Large JSON bodies at the door (issue 32): how long a 50 MB body of a 25M-element array takes
to be refused, and how long `GET /healthz` takes meanwhile (one prober, every 20 ms), on each
JSON operation that could take it; then a real manifest of `--files` files.

    python benchmarks/body.py [--root REPO] [--files 100000] [--only WORDS]

Starts `dgs serve --no-worker` from `--root` (default: this repository; give another checkout
to measure it the same way) on a temporary data folder and a free loopback port. Prints one
line per body; the figures go in docs/benchmarks.md and docs/design.md 5.15.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(root: Path, data: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("DGS_")}
    env.update(DGS_DATA_DIR=str(data), PYTHONPATH=str(root))
    with open(data.parent / "serve.log", "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "core.cli", "serve", "--port", str(port),
                                 "--no-worker"], cwd=root, env=env, stdout=log,
                                stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{url}/healthz", timeout=2).status_code == 200:
                return proc, url
        except httpx.TransportError:
            time.sleep(0.2)
    proc.kill()
    raise SystemExit("dgs serve did not start")


def measure(url: str, path: str, body: bytes) -> str:
    """POST `body` to `path` while a prober times /healthz; a line of what happened."""
    done, latencies = threading.Event(), []

    def probe() -> None:
        with httpx.Client(timeout=900) as c:
            while not done.is_set():
                t = time.perf_counter()
                try:
                    c.get(f"{url}/healthz")
                except httpx.TransportError:
                    pass
                latencies.append(time.perf_counter() - t)
                time.sleep(0.02)

    prober = threading.Thread(target=probe)
    prober.start()
    t = time.perf_counter()
    try:
        status = httpx.post(f"{url}{path}", content=body, timeout=900,
                            headers={"Content-Type": "application/json"}).status_code
    except httpx.TransportError as exc:
        status = type(exc).__name__
    took = time.perf_counter() - t
    done.set()
    prober.join()
    latencies.sort()
    return (f"{len(body) / 1e6:.0f} MB -> {status} in {took:.2f} s; /healthz max "
            f"{latencies[-1]:.3f} s, median {latencies[len(latencies) // 2]:.3f} s "
            f"({len(latencies)} probes)")


def bodies(files: int) -> dict[str, tuple[str, bytes]]:
    array = b"[" + b"0," * (25_000_000 - 1) + b"0]"
    entry = (b'{"path": "images/%06d/cam%03d.png", "size": 1234567, "sha256": "' + b"a" * 64
             + b'"}')
    manifest = b",".join(entry % (i // 100, i % 100) for i in range(files))
    return {"POST /v1/jobs, [0] * 25M": ("/v1/jobs", array),
            "POST /v1/captures, [0] * 25M": ("/v1/captures", array),
            "POST /v1/captures, files: [0] * 25M": ("/v1/captures", (
                b'{"format": "auto", "manifest": {"files": ' + array + b"}}")),
            f"POST /v1/captures, a manifest of {files} files": ("/v1/captures", (
                b'{"format": "auto", "manifest": {"files": [' + manifest + b"]}}"))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=ROOT, help="checkout whose dgs to run")
    parser.add_argument("--files", type=int, default=100_000, help="files of the real manifest")
    parser.add_argument("--only", default="", help="run the bodies whose label has this text "
                        "(a body that held the process for minutes before issue 32 may be "
                        "left out so)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="dgs-body-") as tmp:
        proc, url = start(args.root.resolve(), Path(tmp) / "data")
        try:
            for label, (path, body) in bodies(args.files).items():
                if args.only in label:
                    print(f"{label}: {measure(url, path, body)}", flush=True)
        finally:
            proc.terminate()
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


if __name__ == "__main__":
    main()
