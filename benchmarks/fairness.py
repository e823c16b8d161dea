"""One tenant cannot starve the others (issue 42), measured against a real `dgs serve` with its
embedded workers (SQLite job store and broker; one worker, or `--workers N`): tenant A floods
while tenant B submits a tiny job. Reported for B, idle and under the flood, interleaved in one
run: the job's start (submit to running: the job store's created_at to started_at) and its reads
(`GET /v1/jobs/{id}` every 0.1 s from submit to end).

A's flood, every second until B's job has ended: `--pairs` retry/cancel pairs on A's own
cancelled job (2 x pairs requests at once), `--submits` tiny submits at once (past the
active-jobs cap), and `--streams` event streams held on A's jobs, the retried one and those
accepted (a refused one tries again after its Retry-After); `--submits 0` is the issue's flood.
Between phases A's jobs are cancelled and a probe job of B runs to its end, so every message
the flood left in the queue is gone before the next phase.

    python benchmarks/fairness.py [--rounds 2] [--pairs 15] [--submits 10] [--streams 200]
                                  [--max-active-jobs 2] [--lead 3] [--workers 1]
                                  [--flood-steps 40] [--share-after S]

B's start is also given in two: its wait for a worker (submit to the fair pick) and its pool
process's start (pick to claim), with how many times A's jobs have given a worker up to the
fair share so far. `--flood-steps 3000` makes A's jobs hold the workers for minutes, as a
studio's long reconstructions do; `--share-after 0` turns the fair share off.

The server runs the default limits but DGS_MAX_ACTIVE_JOBS (`--max-active-jobs`, small so
that the flood reaches it). Nothing here depends on how the worker treats the messages of
cancelled jobs: re-run it unchanged after a worker change. Prints the table of
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import collections
import datetime as dt
import json
import os
import random
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from polling import wait_until  # noqa: E402  (beside this script)
from service.client import Client  # noqa: E402
from worker.models import utcnow  # noqa: E402

def tiny(steps: int = 40) -> dict:
    """A tiny job's params: the `test` preset on the 32x32 capture, `steps` steps (B's job and,
    by default, A's: 40)."""
    f = steps / 40
    schedule = {k: max(1, round(v * f)) for k, v in (
        ("stage2_start", 12), ("stage3_start", 28), ("densify_from", 2), ("densify_until", 24),
        ("densify_interval", 4), ("reset_interval", 16), ("sh_interval", 4))}
    return {"preset": "test", "config": {
        "train": {"schedule": {"iterations": steps, **schedule}, "init_points": 300},
        "sequence": {"enabled": False}}}


ACTIVE = ("queued", "running")


def dgs(data: Path, *args: str, **env: str) -> subprocess.Popen | str:
    """`dgs ARGS` on `data`: a server (serve) left running, else the command's output."""
    full = {**{k: v for k, v in os.environ.items() if not k.startswith("DGS_")},
            "DGS_DATA_DIR": str(data), "OMP_NUM_THREADS": "1", **env}
    cmd = [sys.executable, "-m", "core.cli", *args]
    if args[0] == "serve":
        log = open(data.parent / "serve.log", "ab")
        return subprocess.Popen(cmd, cwd=ROOT, env=full, stdout=log, stderr=subprocess.STDOUT)
    return subprocess.run(cmd, cwd=ROOT, env=full, capture_output=True, text=True,
                          check=True).stdout

class Tenant:
    """A tenant's key, its httpx client (answers as they come) and its client library."""

    def __init__(self, url: str, key: str):
        self.headers = {"Authorization": f"Bearer {key}"}
        self.http = httpx.Client(base_url=url, headers=self.headers, timeout=120,
                                 limits=httpx.Limits(max_connections=400))
        self.client = Client(url, key, timeout=120)

    def job(self, job_id: str) -> dict:
        return self.http.get(f"/v1/jobs/{job_id}").json()

    def submit(self, capture: str, steps: int = 40) -> httpx.Response:
        return self.http.post("/v1/jobs", json={"capture_id": capture, "params": tiny(steps)})

    def active(self) -> list[str]:
        return [j["id"] for state in ACTIVE for j in self.http.get(
            "/v1/jobs", params={"state": state, "limit": 200}).json()["items"]]


class Flood:
    """Tenant A's attack, started by `start()` and ended by `stop()` (see the module)."""

    def __init__(self, a: Tenant, url: str, capture: str, target: str, args):
        self.a, self.url, self.capture, self.target, self.args = a, url, capture, target, args
        self.stopped, self.lock = threading.Event(), threading.Lock()
        self.counts: collections.Counter = collections.Counter()
        self.jobs: list[str] = []  # A's accepted jobs: what the streams follow
        self.open = self.most_open = 0
        self.pool = ThreadPoolExecutor(max_workers=2 * args.pairs + args.submits)
        self.threads = [threading.Thread(target=self._bursts, daemon=True)] + [
            threading.Thread(target=self._stream, daemon=True) for _ in range(args.streams)]

    def count(self, what: str, r: httpx.Response) -> httpx.Response:
        code = r.json()["error"]["code"] if r.status_code >= 400 else ""
        with self.lock:
            self.counts[f"{what} {r.status_code} {code}".strip()] += 1
        return r

    def start(self) -> Flood:
        for t in self.threads:
            t.start()
        return self

    def _bursts(self) -> None:
        while not self.stopped.is_set():
            calls = [lambda a=action: self._change(a)
                     for _ in range(self.args.pairs) for action in ("retry", "cancel")]
            calls += [self._submit] * self.args.submits
            list(self.pool.map(lambda call: call(), calls))
            self.stopped.wait(1.0)

    def _change(self, action: str) -> None:
        """A retry or cancel of the target. A keep-alive connection the server closed as it was
        reused (the pool holds 2 x pairs of them, idle between bursts) is counted, not fatal."""
        try:
            self.count(action, self.a.http.post(f"/v1/jobs/{self.target}/{action}"))
        except httpx.TransportError:
            with self.lock:
                self.counts[f"{action} connection lost"] += 1

    def _submit(self) -> None:
        r = self.count("submit", self.a.submit(self.capture, self.args.flood_steps))
        if r.status_code == 202:
            with self.lock:
                self.jobs.append(r.json()["id"])

    def _stream(self) -> None:
        with httpx.Client(base_url=self.url, headers=self.a.headers,
                          timeout=httpx.Timeout(30, read=None)) as http:
            while not self.stopped.is_set():
                with self.lock:  # A's accepted jobs and the one it retries and cancels
                    job = random.choice(self.jobs + [self.target])
                try:
                    self._follow(http, job)
                except httpx.HTTPError:
                    with self.lock:
                        self.counts["stream error"] += 1

    def _follow(self, http: httpx.Client, job: str) -> None:
        with http.stream("GET", f"/v1/jobs/{job}/events") as r:
            if r.status_code != 200:
                r.read()
                self.count("stream", r)
                self.stopped.wait(min(float(r.headers.get("Retry-After", "1")), 10.0))
                return
            with self.lock:
                self.counts["stream 200"] += 1
                self.open += 1
                self.most_open = max(self.most_open, self.open)
            try:
                text = "".join(r.iter_lines())
            finally:
                with self.lock:
                    self.open -= 1
        if job != self.target and any(f'"state":"{s}"' in text
                                      for s in ("succeeded", "failed", "cancelled")):
            with self.lock:  # ended: follow another
                self.jobs = [j for j in self.jobs if j != job]

    def stop(self) -> None:
        """End the attack: no new requests, A's jobs cancelled (which ends its streams)."""
        self.stopped.set()
        self.threads[0].join()
        for job in self.a.active():
            try:
                self.a.client.cancel(job)  # waits out A's own rate limit
            except Exception:  # it ended meanwhile
                pass
        for t in self.threads[1:]:
            t.join(120)
        self.pool.shutdown()


def reads(b: Tenant, job: str, done: threading.Event, out: list[float]) -> None:
    """B's reads of its job every 0.1 s until `done`: each one's latency in ms."""
    while not done.is_set():
        t = time.perf_counter()
        r = b.http.get(f"/v1/jobs/{job}")
        out.append((time.perf_counter() - t) * 1000)
        if r.status_code != 200 or r.json()["state"] not in ACTIVE:
            return
        done.wait(0.1)


def cpu(pid: int) -> float:
    """CPU seconds (user + system) process `pid` has used so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_b(b: Tenant, capture: str, api_pid: int) -> dict:
    """B submits a tiny job, reads it until it ends: its start, the reads' latencies and the
    share of a core the API process used meanwhile (`dgs serve` itself: the worker is its
    child process)."""
    cpu0, t0 = cpu(api_pid), time.monotonic()
    t = time.perf_counter()
    r = b.submit(capture)
    submit_ms = (time.perf_counter() - t) * 1000
    assert r.status_code == 202, r.text
    job, latencies, done = r.json()["id"], [], threading.Event()
    reader = threading.Thread(target=reads, args=(b, job, done, latencies))
    reader.start()
    final = wait_until(lambda: (j := b.job(job))["state"] not in ACTIVE and j, 1800,
                       f"B's job {job} to end", every=0.5)
    done.set()
    reader.join()
    assert final["state"] == "succeeded", final
    start = (dt.datetime.fromisoformat(final["started_at"])
             - dt.datetime.fromisoformat(final["created_at"])).total_seconds()
    return {"start": start, "reads": latencies, "submit_ms": submit_ms, "job": job,
            "api_cpu": (cpu(api_pid) - cpu0) / (time.monotonic() - t0)}


def drained(b: Tenant, a: Tenant, capture: str, broker: Path, api_pid: int) -> None:
    """Until nothing of A is active, the broker holds no waiting message, and a probe job of
    B (last in the queue) has run: every message before it was taken."""
    wait_until(lambda: not a.active(), 600, "A's jobs to end")
    wait_until(lambda: _waiting(broker) == 0, 1800, "the queue to empty", every=1.0)
    run_b(b, capture, api_pid)


def _waiting(broker: Path) -> int:
    with sqlite3.connect(broker, timeout=30) as db:
        return db.execute("SELECT count(*) FROM kombu_message WHERE visible = 1").fetchone()[0]


def ms(values: list[float], q: float) -> float:
    return statistics.quantiles(values, n=100)[int(q) - 1] if len(values) > 1 else values[0]


def split(store: Path, job: str) -> tuple[float, float]:
    """B's start in two: waiting for a worker (created to picked: `worker.fair`) and its pool
    process's start (picked to claimed), from the job store."""
    with sqlite3.connect(store, timeout=30) as db:
        created, picked, started = (dt.datetime.fromisoformat(v) for v in db.execute(
            "SELECT created_at, picked_at, started_at FROM jobs WHERE id = ?", (job,)).fetchone())
    return (picked - created).total_seconds(), (started - picked).total_seconds()


def gave_up(store: Path) -> int:
    """How many times A's jobs gave a worker up: a run that ended "released", or a turn given
    up as its pool process started (a line of the job's log, no run)."""
    with sqlite3.connect(store, timeout=30) as db:
        runs = sum(1 for (runs,) in db.execute("SELECT runs FROM jobs WHERE tenant = 'flooder'")
                   for run in json.loads(runs or "[]") if run.get("outcome") == "released")
        turns = db.execute(
            "SELECT COUNT(*) FROM job_logs JOIN jobs ON jobs.id = job_logs.job_id WHERE "
            "jobs.tenant = 'flooder' AND job_logs.line LIKE '%its turn goes to%'").fetchone()[0]
    return runs + turns


def row(phase: str, out: dict, flood: Flood | None, store: Path) -> str:
    r = out["reads"]
    wait, start = split(store, out["job"])
    attack = "" if flood is None else "; ".join(
        f"{k}: {v}" for k, v in sorted(flood.counts.items())) + \
        f"; streams open at once, most: {flood.most_open}"
    return (f"| {phase} | {out['start']:.1f} | {wait:.1f} | {start:.1f} | {gave_up(store)} | "
            f"{out['submit_ms']:.0f} | {len(r)} | "
            f"{ms(r, 50):.1f} | {ms(r, 95):.1f} | {max(r):.1f} | {100 * out['api_cpu']:.0f} | "
            f"{attack} |")


def summary(starts: dict[str, list[float]]) -> str:
    """B's starts idle and flooded side by side: median, mean, worst, and flooded over idle."""
    stats = {phase: (statistics.median(v), statistics.fmean(v), max(v))
             for phase, v in starts.items()}
    (mi, ai, wi), (mf, af, wf) = stats["idle"], stats["flood"]
    return (f"B's start over {len(starts['idle'])} rounds, idle / flood, s: median {mi:.2f} / "
            f"{mf:.2f} ({mf / mi:.1f}x), mean {ai:.2f} / {af:.2f} ({af / ai:.1f}x), worst "
            f"{wi:.2f} / {wf:.2f} ({wf / wi:.1f}x)")


def setup(args, data: Path) -> tuple[subprocess.Popen, str, Tenant, Tenant, str, str, str]:
    """The server, its URL, tenants A and B, their captures and A's cancelled job."""
    keys = {t: dgs(data, "keys", "create", "--tenant", t).strip().splitlines()[-1]
            for t in ("flooder", "victim")}
    port = 8400 + random.randrange(500)
    share = {} if args.share_after is None else {
        "DGS_SHARE_AFTER_SECONDS": str(args.share_after)}
    server = dgs(data, "serve", "--port", str(port), "--workers", str(args.workers),
                 DGS_MAX_ACTIVE_JOBS=str(args.max_active_jobs), DGS_QUEUE=f"fair-{port}",
                 **share)
    url = f"http://127.0.0.1:{port}"
    wait_until(lambda: _ready(url), 120, "dgs serve")
    for i in range(args.workers):  # worker.log, worker-2.log, ...
        log = data / "logs" / ("worker.log" if i == 0 else f"worker-{i + 1}.log")
        wait_until(lambda: " ready." in _text(log), 300, "the workers")
    a, b = Tenant(url, keys["flooder"]), Tenant(url, keys["victim"])
    folder = data.parent / "capture"
    dgs(data, "synth", str(folder), "--frames", "1", "--views", "8", "--size", "32", "32")
    captures = []
    for t in (a, b):
        cap = t.client.create_capture(folder)
        t.client.upload_capture(cap["id"], folder)
        t.client.commit(cap["id"])
        captures.append(cap["id"])
    target = a.submit(captures[0], args.flood_steps).json()["id"]  # to retry and cancel
    a.client.cancel(target)
    return server, url, a, b, captures[0], captures[1], target


def _ready(url: str) -> bool:
    try:
        return httpx.get(f"{url}/readyz", timeout=5).status_code == 200
    except httpx.TransportError:
        return False


def _text(path: Path) -> str:
    return path.read_text(errors="replace") if path.is_file() else ""


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--pairs", type=int, default=15)
    p.add_argument("--submits", type=int, default=10)
    p.add_argument("--streams", type=int, default=200)
    p.add_argument("--max-active-jobs", type=int, default=2)
    p.add_argument("--workers", type=int, default=1,
                   help="embedded workers (`dgs serve --workers N`)")
    p.add_argument("--flood-steps", type=int, default=40,
                   help="steps of A's jobs (long ones hold the workers)")
    p.add_argument("--share-after", type=float, default=None, metavar="S",
                   help="the server's DGS_SHARE_AFTER_SECONDS (default: its own; 0: off)")
    p.add_argument("--lead", type=float, default=3.0,
                   help="seconds of flood (or idle) before B submits")
    args = p.parse_args()
    data = Path(tempfile.mkdtemp(prefix="dgs-fairness-")) / "data"
    data.mkdir(parents=True)
    print(f"load before: {os.getloadavg()}; {utcnow():%Y-%m-%d %H:%M} UTC; data {data}")
    server, url, a, b, cap_a, cap_b, target = setup(args, data)
    broker, store = data / "broker.sqlite3", data / "dgs.sqlite3"
    try:
        pid = server.pid
        drained(b, a, cap_b, broker, pid)  # warms the worker (its native build, the imports)
        rows, starts = [], {"idle": [], "flood": []}
        for i in range(args.rounds):
            time.sleep(args.lead)
            out = run_b(b, cap_b, pid)
            starts["idle"].append(out["start"])
            rows.append(row(f"idle, round {i + 1}", out, None, store))
            drained(b, a, cap_b, broker, pid)
            flood = Flood(a, url, cap_a, target, args).start()
            time.sleep(args.lead)
            out = run_b(b, cap_b, pid)
            flood.stop()
            starts["flood"].append(out["start"])
            rows.append(row(f"flood, round {i + 1}", out, flood, store))
            drained(b, a, cap_b, broker, pid)
        print("| B's job | start s | of it, for a worker | its process | A's jobs gave up, "
              "so far | submit ms | reads | p50 ms | p95 ms | max ms | API CPU % "
              "| A's answers |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|")
        print("\n".join(rows))
        print(summary(starts))
    finally:
        server.terminate()
        server.wait(60)
        print(f"load after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
