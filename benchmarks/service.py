"""Service benchmarks (issue 6): upload throughput over loopback against a plain file copy of the
same bytes, and the latency of `GET /v1/jobs/{id}` with 50 concurrent pollers while a job runs
(pollers that ask once a second, as a progress page does; then pollers that ask again as soon as
they are answered, which measures the API's saturation rather than a poller's wait).

    python benchmarks/service.py [--size-mb 1024] [--pollers 50] [--seconds 30] [--interval 1]

Each part starts its own `dgs serve` (embedded default: SQLite, local store, one worker) in a
temporary folder on this machine and talks to it over loopback with the project's client
(service.client, in both of its upload modes).
Prints tables; the figures go in docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.client import Client  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """`dgs serve` in a subprocess on a free loopback port, with its own data folder."""

    def __init__(self, data: Path, worker: bool = True):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {**os.environ, "DGS_DATA_DIR": str(data)}
        cmd = [sys.executable, "-m", "core.cli", "serve", "--port", str(self.port)]
        if not worker:
            cmd.append("--no-worker")
        self.log = open(data.parent / f"serve-{self.port}.log", "wb")
        self.proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=self.log,
                                     stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"{self.url}/healthz", timeout=1).status_code == 200:
                    return
            except httpx.TransportError:
                time.sleep(0.2)
        raise RuntimeError(f"dgs serve did not start; see {self.log.name}")

    def cpu(self) -> float:
        """CPU seconds (user + system) the server process has used so far."""
        fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        self.log.close()


UPLOAD_MODES = (("upload, streamed (one PATCH per file; the client's default)", None),
                ("upload, 8 MiB PATCHes with a SHA-1 each", "sha1"))


def bench_upload(tmp: Path, size_mb: int, repeats: int) -> list[dict]:
    """Seconds to copy a file (shutil.copyfile + fsync, same disk) against uploading it to the
    service (tus, the file verified against its SHA-256 and fsynced by the server) with each
    client mode; the runs interleave (copy, upload, upload, copy, ...) so that the machine's
    load drifts across all of them alike; each row is the best of `repeats`, with the median
    CPU seconds it used (copy: this process; upload: client and server processes together),
    which a busy machine changes less than the wall-clock time."""
    src_dir = tmp / "upload-src"
    src_dir.mkdir()
    src = src_dir / "images" / "000000" / "cam00.png"
    src.parent.mkdir(parents=True)
    with open(src, "wb") as f:  # incompressible bytes (no filesystem or transport tricks)
        for _ in range(size_mb):
            f.write(os.urandom(1 << 20))
    nbytes = src.stat().st_size
    times: dict[str, list[float]] = {"copy": [], **{m: [] for m, _ in UPLOAD_MODES}}
    cpu: dict[str, list[float]] = {k: [] for k in times}
    server = Server(tmp / "upload-data", worker=False)
    try:
        for i in range(repeats):
            dest = tmp / f"copy-{i}.bin"
            os.sync()
            t0, c0 = time.perf_counter(), time.process_time()
            shutil.copyfile(src, dest)
            with open(dest, "rb+") as f:  # the copy counts once it is on disk, like an upload
                os.fsync(f.fileno())
            times["copy"].append(time.perf_counter() - t0)
            cpu["copy"].append(time.process_time() - c0)
            dest.unlink()
            for mode, checksum in UPLOAD_MODES:
                with Client(server.url, chunk_checksum=checksum) as client:
                    cap = client.create_capture(src_dir)
                    os.sync()
                    t0, c0, s0 = time.perf_counter(), time.process_time(), server.cpu()
                    client.upload_capture(cap["id"], src_dir)
                    times[mode].append(time.perf_counter() - t0)
                    cpu[mode].append(time.process_time() - c0 + server.cpu() - s0)
                    state = client.capture(cap["id"])["files"]
                    assert state["received"] == 1 and state["received_bytes"] == nbytes, state
                    client.http.delete(f"/v1/captures/{cap['id']}")  # free the disk
    finally:
        server.stop()
    copy_s = min(times["copy"])
    rows = [{"what": "file copy (shutil.copyfile + fsync)", "MB": nbytes / 1e6, "s": copy_s,
             "MB/s": nbytes / 1e6 / copy_s, "vs copy": 1.0,
             "CPU s": statistics.median(cpu["copy"])}]
    for mode, _ in UPLOAD_MODES:
        best = min(times[mode])
        rows.append({"what": mode, "MB": nbytes / 1e6, "s": best, "MB/s": nbytes / 1e6 / best,
                     "vs copy": copy_s / best, "CPU s": statistics.median(cpu[mode])})
    return rows


async def _pollers(url: str, path: str, pollers: int, seconds: float,
                   interval: float | None) -> tuple[list[float], int]:
    """`pollers` concurrent clients on one event loop, each with its own keep-alive
    connection: each sends GET `path`, reads the whole answer, then (with `interval`) sleeps
    until its next tick, ticks spread evenly over the interval; without it, sends the next
    request at once.

    A lean HTTP/1.1 client on asyncio streams (as load generators such as wrk are lean), so the
    latencies are the server's: 50 httpx.AsyncClient instances in one loop cost more than the
    server does, and their latency grows with their number at the same request rate (p50 73 ms
    with 50 of them against 5 ms with one, both at 50 requests/s, on an idle machine), which is
    the client's, not the server's (see `_httpx_pollers`)."""
    import asyncio
    from urllib.parse import urlsplit

    host, port = urlsplit(url).hostname, urlsplit(url).port
    request = f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\n\r\n".encode()
    latencies: list[float] = []
    errors = 0
    stop = time.monotonic() + seconds

    async def poll(i: int) -> None:
        nonlocal errors
        reader, writer = await asyncio.open_connection(host, port)
        try:
            if interval:
                await asyncio.sleep(interval * i / pollers)
            tick = time.monotonic()
            while time.monotonic() < stop:
                t0 = time.perf_counter()
                writer.write(request)
                await writer.drain()
                head = await reader.readuntil(b"\r\n\r\n")
                lines = head.split(b"\r\n")
                length = next((int(line.split(b":", 1)[1]) for line in lines
                               if line.lower().startswith(b"content-length:")), None)
                if length is None:
                    raise RuntimeError(f"no Content-Length in the answer: {head[:200]!r}")
                await reader.readexactly(length)
                latencies.append(time.perf_counter() - t0)
                errors += lines[0].split(b" ")[1] != b"200"
                if interval:
                    tick += interval
                    await asyncio.sleep(max(0.0, tick - time.monotonic()))
        finally:
            writer.close()

    await asyncio.gather(*(poll(i) for i in range(pollers)))
    return latencies, errors


async def _httpx_pollers(url: str, path: str, pollers: int, seconds: float,
                         interval: float) -> tuple[list[float], int]:
    """The same pollers as `_pollers`, each an httpx.AsyncClient (what the first version of this
    benchmark used): shows what a Python client adds to the latency it measures."""
    import asyncio

    latencies: list[float] = []
    errors = 0
    stop = time.monotonic() + seconds

    async def poll(i: int) -> None:
        nonlocal errors
        async with httpx.AsyncClient(base_url=url, timeout=30) as http:
            await asyncio.sleep(interval * i / pollers)
            tick = time.monotonic()
            while time.monotonic() < stop:
                t0 = time.perf_counter()
                r = await http.get(path)
                latencies.append(time.perf_counter() - t0)
                errors += r.status_code != 200
                tick += interval
                await asyncio.sleep(max(0.0, tick - time.monotonic()))

    await asyncio.gather(*(poll(i) for i in range(pollers)))
    return latencies, errors


def bench_polling(tmp: Path, pollers: int, seconds: float, interval: float) -> list[dict]:
    """Latency of GET /v1/jobs/{id} from `pollers` concurrent clients while the embedded
    worker runs a reconstruction on the same machine: pollers that ask every `interval`
    seconds (a progress page), then pollers that ask again as soon as answered (saturation)."""
    import asyncio

    from core.synth import SynthConfig, synthesize

    capture = tmp / "poll-capture"
    synthesize(capture, SynthConfig(frames=1, views=16, width=64, height=64, seed=1,
                                    ao_directions=8))
    server = Server(tmp / "poll-data", worker=True)
    rows = []
    try:
        client = Client(server.url)
        cap = client.create_capture(capture)
        client.upload_capture(cap["id"], capture)
        client.commit(cap["id"])
        job = client.submit(cap["id"], {"preset": "test", "config": {
            "train": {"schedule": {"iterations": 100_000}}}})  # runs past the measurement
        deadline = time.monotonic() + 600
        while client.job(job["id"])["progress"]["iteration"] < 10:
            if time.monotonic() > deadline:
                raise RuntimeError("the job did not start training within 10 minutes")
            time.sleep(0.5)
        modes = ((f"every {interval:g} s", interval, _pollers),
                 ("back to back", None, _pollers),
                 (f"every {interval:g} s, httpx clients", interval, _httpx_pollers))
        for mode, every, run in modes:
            latencies, errors = asyncio.run(run(server.url, f"/v1/jobs/{job['id']}",
                                                pollers, seconds, every))
            state = client.job(job["id"])
            ms = sorted(x * 1000 for x in latencies)
            rows.append({"pollers": pollers, "each polls": mode, "requests": len(ms),
                         "req/s": len(ms) / seconds, "p50 ms": statistics.median(ms),
                         "p99 ms": ms[int(0.99 * (len(ms) - 1))], "max ms": ms[-1],
                         "errors": errors, "job": f"{state['state']} at step "
                                                 f"{state['progress']['iteration']}"})
        client.cancel(job["id"])
        client.close()
    finally:
        server.stop()
    return rows


def table(rows: list[dict]) -> str:
    keys = list(rows[0])
    fmt = lambda v: f"{v:,.2f}" if isinstance(v, float) else str(v)  # noqa: E731
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(fmt(r[k]) for k in keys) + " |" for r in rows]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size-mb", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--pollers", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--interval", type=float, default=1.0,
                    help="seconds between two polls of one poller (first polling table)")
    ap.add_argument("--only", choices=("upload", "polling"), default=None,
                    help="run one part")
    ap.add_argument("--json", default=None, help="also write the results here")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="dgs-bench-", dir=os.environ.get("TMPDIR")) as d:
        tmp = Path(d)
        upload = polling = None
        if args.only in (None, "upload"):
            upload = bench_upload(tmp, args.size_mb, args.repeats)
            print("\nUpload over loopback against a file copy (best of", args.repeats,
                  "runs)\n")
            print(table(upload), flush=True)
        if args.only in (None, "polling"):
            polling = bench_polling(tmp, args.pollers, args.seconds, args.interval)
            print(f"\nGET /v1/jobs/{{id}} with {args.pollers} concurrent pollers while a job "
                  "runs\n")
            print(table(polling))
    if args.json:
        Path(args.json).write_text(json.dumps({"upload": upload, "polling": polling}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
