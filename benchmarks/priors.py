"""The synthetic figure without its normal priors (issue 39): how close the rig's own priors
(`core.rig`, the default for a capture without `normals/`) bring the geometry to a run given
the capture's priors, against no prior term at all.

One `dgs synth` scene per size, written twice from the same seed: with `--priors` (the
capture's degraded normals in `normals/`) and without. Three runs on it, each `dgs reconstruct`
then `dgs eval` (held-out cameras, normal cosine against the ground truth, the mesh's Chamfer
distance):

- **capture's priors**: the capture with `normals/`;
- **rig's priors**: the capture without, as a studio's capture comes (the default);
- **none**: the capture without, `rig_priors` off (no prior term).

    python benchmarks/priors.py [--sizes test:12:64 fast:16:128] [--seeds 0] [--threads 1]
                                [--work DIR] [--runs capture rig none] [--set KEY=VALUE ...]

With `--work`, runs an earlier call finished there are read, not run again. `--set` lays a
setting on every row (`train.losses.normal_confidence=by_source`); the runs' folders are named
by the settings, so one `--work` keeps runs with and without them apart.

Each size is PRESET:VIEWS:PIXELS. Prints the table of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks.panoptic import lay_setting  # noqa: E402

RUNS = {"capture's priors": (True, {}), "rig's priors": (False, {}),
        "none": (False, {"rig_priors": False})}


def short(name: str) -> str:
    """A row's name on the command line and in file names: `capture`, `rig`, `none`."""
    return name.split("'")[0].strip()


def dgs(*args: str, threads: int) -> None:
    """`dgs ARGS` in a child process, stopped with this one (a killed benchmark leaves no run
    training: `main` turns SIGTERM into an exit)."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    cmd = [sys.executable, "-m", "core.cli", *args]
    child = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL)
    try:
        code = child.wait()
    finally:
        if child.poll() is None:
            child.terminate()
            child.wait()
    if code:
        raise subprocess.CalledProcessError(code, cmd)


def one(work: Path, preset: str, views: int, pixels: int, seed: int, name: str,
        threads: int, settings: tuple[str, ...] = ()) -> dict:
    priors, config = RUNS[name]
    config = copy.deepcopy(config)
    for setting in settings:
        lay_setting(config, setting)
    capture = work / f"{preset}-{views}-{pixels}-{seed}-{'priors' if priors else 'bare'}"
    if not capture.exists():
        dgs("synth", str(capture), "--frames", "1", "--views", str(views), "--size",
            str(pixels), str(pixels), "--seed", str(seed), *(["--priors"] if priors else []),
            threads=threads)
    tag = "".join(f"-{k.rpartition('.')[2]}={v}"  # -normal_confidence=by_source
                  for k, _, v in (s.partition("=") for s in settings))
    run = work / f"run-{preset}-{views}-{pixels}-{seed}-{short(name)}{tag}"
    cfg = work / f"{run.name}.json"
    cfg.write_text(json.dumps(config))
    timing = work / f"{run.name}.seconds"
    if not (run / "eval.json").is_file():  # a run of an earlier call is kept (--work)
        shutil.rmtree(run, ignore_errors=True)
        t = time.perf_counter()
        dgs("reconstruct", str(capture), "--out", str(run), "--preset", preset, "--config",
            str(cfg), "--no-progress", threads=threads)
        timing.write_text(str(time.perf_counter() - t))
        dgs("eval", str(run), threads=threads)
    seconds = float(timing.read_text()) if timing.is_file() else float("nan")
    ev = json.loads((run / "eval.json").read_text())
    frames = json.loads((run / "metrics.json").read_text())["frames"]  # {frame: record}
    prior = next(iter(frames.values())).get("normal_prior")
    return {"psnr": ev["psnr"], "cos": ev["normal_cos"], "deg": ev["normal_deg"],
            "chamfer": (ev.get("mesh") or {}).get("chamfer_relative"), "seconds": seconds,
            "prior": prior}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", nargs="+", default=["test:12:64", "fast:16:128"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--work", type=Path, default=None)
    p.add_argument("--runs", nargs="+", choices=[short(n) for n in RUNS],
                   default=None, help="only these rows (default: all three)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a setting laid on every row (a dotted key of the run's config)")
    args = p.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    work = args.work or Path(tempfile.mkdtemp(prefix="dgs-priors-"))
    work.mkdir(parents=True, exist_ok=True)
    print(f"load before: {os.getloadavg()}; work {work}")
    print("| preset, views, pixels | priors | seeds | held-out PSNR | normal cosine (deg) | "
          "mesh Chamfer, % of diagonal | s a run |")
    print("|---|---|---|---|---|---|---|")
    for size in args.sizes:
        preset, views, pixels = size.split(":")
        for name in RUNS:
            if args.runs and short(name) not in args.runs:
                continue
            rs = [one(work, preset, int(views), int(pixels), s, name, args.threads,
                      tuple(args.set)) for s in args.seeds]
            mean = {k: statistics.mean(r[k] for r in rs) for k in ("psnr", "cos", "deg",
                                                                    "seconds")}
            chamfers = [r["chamfer"] for r in rs if r["chamfer"] is not None]
            chamfer = f"{100 * statistics.mean(chamfers):.2f}" if chamfers else "-"
            print(f"| {preset}, {views}, {pixels} | {name} | {len(rs)} | {mean['psnr']:.2f} | "
                  f"{mean['cos']:.3f} ({mean['deg']:.1f}) | {chamfer} | "
                  f"{mean['seconds']:.0f} |", flush=True)
    print(f"load after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
