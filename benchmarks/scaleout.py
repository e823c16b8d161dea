"""A sequence job on 1 and on 2 workers of one thread each (issue 22: "groups of pictures in
parallel across workers"): wall time, speed-up, and whether the frames are the serial run's.

One `dgs synth` capture of `--frames` frames cut into groups of `--gop` (at least 4 groups) is
reconstructed three ways: `dgs reconstruct` in one process (the serial run), and through a
real `dgs serve --workers N` (API, SQLite job store and broker, local artifacts) for each N of
`--workers`, where the job runs as one part per group on whichever worker is idle and is then
assembled (merge, evaluation, publishing). Every process trains on one thread. The service's
wall time runs from the job's submission to its end (the workers are started and connected
before); the parts' own times and the assembly come from the job's parts. Quality: held-out
PSNR from eval.json, and whether every frame's PLY is the serial run's to the bit (groups are
independent with `sequence.refine_scope` "group", and one thread makes each reproducible).

    python benchmarks/scaleout.py [--out DIR] [--frames 8] [--gop 2] [--size 48]
                                  [--views 8] [--iterations 1200] [--workers 1,2] [--quick]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from polling import wait_until  # noqa: E402  (beside this script)


def config(iterations: int) -> dict:
    """The `test` preset's plan at `iterations` steps a key frame, meshes off."""
    f = iterations / 500
    s = {"stage2_start": 117, "stage3_start": 350, "densify_from": 8, "densify_until": 250,
         "densify_interval": 2, "reset_interval": 50, "sh_interval": 17}
    return {"train": {"schedule": {"iterations": iterations,
                                   **{k: max(1, round(v * f)) for k, v in s.items()}}},
            "mesh": {"enabled": False}}


def env_for(data: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("DGS_")}
    env.update({"DGS_DATA_DIR": str(data), "OMP_NUM_THREADS": "1", "DGS_TORCH_THREADS": "1"})
    env.update(extra)
    return env


def digests(run: Path, frames: list[str]) -> dict[str, str]:
    return {f: hashlib.sha256((run / "frames" / f / "gaussians.ply").read_bytes()).hexdigest()
            for f in frames}


def serial(capture: Path, out: Path, cfg: Path, gop: int) -> dict:
    run = out / "serial"
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "core.cli", "reconstruct", str(capture), "--out",
                    str(run), "--preset", "test", "--gop", str(gop), "--config", str(cfg),
                    "--no-progress"], check=True, cwd=ROOT, env=env_for(out / "unused"),
                   stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    subprocess.run([sys.executable, "-m", "core.cli", "eval", str(run)], check=True, cwd=ROOT,
                   env=env_for(out / "unused"), stdout=subprocess.DEVNULL)
    return {"wall": wall, "run": run, "eval": json.loads((run / "eval.json").read_text())}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]

def service(capture: Path, out: Path, params: dict, workers: int) -> dict:
    import httpx

    from service.client import Client

    data, port = out / f"service-{workers}" / "data", _free_port()
    data.mkdir(parents=True)
    log = open(data.parent / "serve.log", "wb")
    proc = subprocess.Popen([sys.executable, "-m", "core.cli", "serve", "--port", str(port),
                             "--workers", str(workers)], cwd=ROOT, stdout=log,
                            stderr=subprocess.STDOUT, env=env_for(data, DGS_QUEUE=f"b{port}"))
    url = f"http://127.0.0.1:{port}"
    try:
        def ready() -> bool:
            try:
                return httpx.get(f"{url}/readyz", timeout=5).status_code == 200
            except httpx.TransportError:
                return False

        wait_until(ready, 120, "dgs serve", every=0.3)
        logs = ["worker.log"] + [f"worker-{i + 1}.log" for i in range(1, workers)]
        wait_until(lambda: all((data / "logs" / n).is_file() and " ready." in (
            data / "logs" / n).read_text(errors="replace") for n in logs), 300, "the workers",
            every=0.3)
        with Client(url) as client:
            cap = client.create_capture(capture)
            client.upload_capture(cap["id"], capture)
            client.commit(cap["id"], timeout=300)
            start = time.perf_counter()
            job = client.submit(cap["id"], params)
            done = client.wait(job["id"], timeout=7200)
            wall = time.perf_counter() - start
            if done["state"] != "succeeded":
                raise RuntimeError(f"job {done['state']}: {done.get('error')}")
            run = data.parent / "run"
            client.download_all(job["id"], run)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=120)
        log.close()
    return {"wall": wall, "run": run, "job": done,
            "eval": json.loads((run / "eval.json").read_text())}


def _seconds(a: str, b: str) -> float:
    from datetime import datetime

    return (datetime.fromisoformat(b) - datetime.fromisoformat(a)).total_seconds()


def part_times(job: dict) -> tuple[list[float], float]:
    """Each part's wall seconds, and the assembly's (the last part's end to the job's)."""
    parts = job.get("parts") or []
    spans = [_seconds(p["started_at"], p["finished_at"]) for p in parts]
    last = max(p["finished_at"] for p in parts)
    return spans, _seconds(last, job["finished_at"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--gop", type=int, default=2)
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=1200)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--quick", action="store_true", help="300 steps a key frame")
    args = ap.parse_args()
    if args.quick:
        args.iterations = 300
    from core.synth import SynthConfig, synthesize

    out = args.out or Path(tempfile.mkdtemp(prefix="dgs-scaleout-"))
    capture = out / "capture"
    synthesize(capture, SynthConfig(frames=args.frames, views=args.views, width=args.size,
                                    height=args.size, seed=0))
    cfg = config(args.iterations)
    (out / "config.json").write_text(json.dumps(cfg))
    frames = [f"{i:06d}" for i in range(args.frames)]
    groups = -(-args.frames // args.gop)
    print(f"{args.frames} frames, {groups} groups of {args.gop}, {args.size}x{args.size}, "
          f"{args.views} views, {args.iterations} steps a key frame, one thread a process; "
          f"in {out}", flush=True)
    ref = serial(capture, out, out / "config.json", args.gop)
    ref_digest = digests(ref["run"], frames)
    rows = [("`dgs reconstruct` (serial)", ref, None)]
    for n in [int(w) for w in args.workers.split(",")]:
        params = {"preset": "test", "gop": args.gop, "config": cfg}
        before = os.getloadavg()[0]
        result = service(capture, out, params, n)
        rows.append((f"`dgs serve --workers {n}`", result, n))
        # The machine's other users show in the load (this run alone adds about n).
        print(f"  {n} worker(s): {result['wall']:.1f} s (load average {before:.1f} before, "
              f"{os.getloadavg()[0]:.1f} after)", flush=True)
    one = next((r for _, r, n in rows if n == 1), None)
    print("\n| run | wall s | speed-up vs 1 worker | parts (s each) | assembly s | held-out "
          "PSNR | PLYs identical to serial |\n| --- | --- | --- | --- | --- | --- | --- |")
    for name, r, n in rows:
        same = sum(digests(r["run"], frames)[f] == ref_digest[f] for f in frames)
        spans, assembly = part_times(r["job"]) if n else ([], None)
        speed = f"{one['wall'] / r['wall']:.2f}x" if one is not None and n else "-"
        print(f"| {name} | {r['wall']:.1f} | {speed} | "
              f"{', '.join(f'{s:.1f}' for s in spans) or '-'} | "
              f"{'-' if assembly is None else f'{assembly:.1f}'} | {r['eval']['psnr']:.3f} | "
              f"{same}/{len(frames)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
