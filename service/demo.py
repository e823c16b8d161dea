"""`dgs demo` through the HTTP service (what `make demo` runs when the service extra is
installed): the main job as a studio would run it.

synth the capture -> start an embedded `dgs serve` (a subprocess on a free loopback port, its
own data folder under the demo's) -> upload the capture with the client (tus) -> submit the
reconstruct job -> follow its server-sent events as a progress bar -> download the artifacts ->
evaluate and make the contact sheet here -> stop the server.

The command keeps core's `dgs demo` arguments (core.demo.commands registers it; this module
takes it over through the dgs.commands entry point, see service.commands).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx

from service.client import Client, JobBars
from service.settings import ServiceSettings

__all__ = ["DemoServer", "run_service_demo"]

STEPS = 6


class DemoServer:
    """`dgs serve` with its embedded worker in a subprocess: a free loopback port, the data
    folder `data_dir`, none of the caller's DGS_* service settings (the demo stands alone)."""

    def __init__(self, data_dir: Path, *, start_timeout: float = 120.0):
        self.data_dir = data_dir
        data_dir.mkdir(parents=True, exist_ok=True)
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        ours = {f"DGS_{name.upper()}" for name in ServiceSettings.model_fields}
        env = {k: v for k, v in os.environ.items() if k not in ours}
        self.log_path = data_dir / "serve.log"
        self._log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "core.cli", "serve", "--port", str(self.port),
             "--data-dir", str(data_dir)], env=env, stdout=self._log,
            stderr=subprocess.STDOUT, cwd=Path(__file__).resolve().parents[1])
        try:
            self._wait_ready(start_timeout)
        except BaseException:
            self.stop()
            raise

    def _wait_ready(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"dgs serve exited ({self.proc.returncode}); see "
                                   f"{self.log_path}")
            try:
                if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"dgs serve did not answer within {timeout:.0f} s; see "
                           f"{self.log_path}")

    @property
    def worker_log(self) -> Path:
        return self.data_dir / "logs" / "worker.log"

    def stop(self) -> int | None:
        """SIGTERM (the server stops its worker too), SIGKILL after a minute."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return self.proc.returncode

    def __enter__(self) -> DemoServer:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def _upload(client, capture_dir: Path) -> dict:
    capture = client.create_capture(capture_dir, name="dgs demo")
    total = capture["total_bytes"]
    t0 = time.perf_counter()
    client.upload_capture(capture["id"], capture_dir)
    took = time.perf_counter() - t0
    print(f"      {capture['files']['declared']} files, {total / 1e6:.1f} MB in {took:.1f} s "
          f"(tus); committing", flush=True)
    return client.commit(capture["id"])


def _follow(client, job_id: str, server: DemoServer) -> dict:
    bars = JobBars()  # the job's bar, and one per running part of a sequence run as parts
    try:
        job = client.wait(job_id, on_event=bars.on_event)
    finally:
        bars.close()
    if job["state"] != "succeeded":
        error = (job.get("error") or {}).get("message", "")
        tail = "\n".join(client.logs(job_id)[-15:])
        raise RuntimeError(f"job {job_id} {job['state']}: {error}\n{tail}\n(worker log: "
                           f"{server.worker_log})")
    return job


def _interrupted(signum, frame) -> None:
    raise KeyboardInterrupt


def run_service_demo(out: str = "demo", *, synth: dict | None = None,
                     overrides: dict | None = None, preset: str = "test") -> int:
    """The demo through the service (see the module docstring); `synth` (SynthConfig fields)
    and `overrides` (the job's config) default to core's demo."""
    # lazy: the demo's capture loads torch; `dgs serve` and the API import this module
    from core.demo import DEMO_OVERRIDES, demo_capture, report
    from core.evaluation import evaluate_run  # lazy: torch too (the held-out renders)

    root = Path(out)
    capture_dir, run_dir, data_dir = root / "capture", root / "run", root / "service"
    overrides = DEMO_OVERRIDES if overrides is None else overrides
    t0 = time.perf_counter()
    capture = demo_capture(capture_dir, synth, step=f"[1/{STEPS}]")
    shutil.rmtree(data_dir, ignore_errors=True)  # each demo starts a fresh service
    print(f"[2/{STEPS}] dgs serve --port ... --data-dir {data_dir} (API and embedded worker)",
          flush=True)
    # SIGTERM (a CI timeout, `kill`) ends the demo like Ctrl-C: the server is stopped too.
    main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _interrupted) if main else None
    try:
        job, files, train_s = _run_job(data_dir, capture_dir, run_dir, overrides, preset)
    finally:
        if main:
            signal.signal(signal.SIGTERM, previous)
    print(f"      server stopped (its data: {data_dir})", flush=True)
    result = evaluate_run(run_dir, capture_dir)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    report(capture, capture_dir, run_dir, metrics, result, train_s, step=f"[6/{STEPS}]")
    print(f"      PLY per frame: {run_dir / 'frames'}")
    print(f"      total {time.perf_counter() - t0:.0f} s")
    print(f"open it in a browser: DGS_DATA_DIR={data_dir} {Path(sys.executable).parent / 'dgs'} "
          "serve --port 8000, then http://127.0.0.1:8000/ : panel 2 has the job, panel 5 "
          "plays its stream relit live")
    return 0


def _run_job(data_dir: Path, capture_dir: Path, run_dir: Path, overrides: dict,
             preset: str) -> tuple[dict, list[Path], float]:
    """Steps 2 to 5: serve, upload, run the job, download; the server is stopped after."""
    with DemoServer(data_dir) as server, Client(server.url) as client:
        print(f"      {server.url} (OpenAPI: {server.url}/docs), worker log "
              f"{server.worker_log}", flush=True)
        print(f"[3/{STEPS}] upload {capture_dir} -> POST /v1/captures, tus /v1/uploads",
              flush=True)
        cap = _upload(client, capture_dir)
        iterations = overrides.get("train", {}).get("schedule", {}).get("iterations")
        print(f"[4/{STEPS}] POST /v1/jobs reconstruct ({preset} preset"
              f"{f', {iterations} iterations' if iterations else ''}; the worker builds the "
              "native rasterizer on first use)", flush=True)
        t1 = time.perf_counter()
        job = client.submit(cap["id"], {"preset": preset, "config": overrides},
                            name="dgs demo")
        print(f"      job {job['id']}: {server.url}{job['links']['self']}", flush=True)
        job = _follow(client, job["id"], server)
        train_s = time.perf_counter() - t1
        if run_dir.exists():
            shutil.rmtree(run_dir)  # an earlier demo's results
        print(f"[5/{STEPS}] download the artifacts -> {run_dir}", flush=True)
        files = client.download_all(job["id"], run_dir)
        print(f"      {len(files)} files, {sum(p.stat().st_size for p in files) / 1e6:.1f} MB",
              flush=True)
        _export(client, job["id"], run_dir)
    return job, files, train_s


def _export(client, job_id: str, run_dir: Path) -> None:
    """The reconstruction as the relightable stream the page's player plays (an export job)."""
    exp = client.wait(client.export(job_id, ("stream",), name="dgs demo")["id"])
    if exp["state"] != "succeeded":
        raise RuntimeError(f"the export job {exp['id']} {exp['state']}: {exp.get('error')}")
    for kind in ("export", "stream"):  # the record, and the stream to open anywhere
        client.download_all(exp["id"], run_dir, kind=kind)
    stream = json.loads((run_dir / "export" / "export.json").read_text())["stream"]
    print(f"      stream (POST /v1/exports): {stream['bytes_per_frame'] / 1e3:.1f} kB a frame, "
          f"{stream['ratio_to_ply']:.1f}x smaller than the PLY", flush=True)
