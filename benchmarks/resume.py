"""A reconstruction killed with SIGKILL and continued with `--resume`, against the same run left
alone (issue 4: "a killed `dgs reconstruct --resume` continues from its last checkpoint and
reaches the same quality").

Both runs are real `dgs reconstruct` processes on one `dgs synth` capture with the same preset
and overrides (the demo's by default). The second is killed part-way between two checkpoints
(after the `--kill-after`-th checkpoint, half a checkpoint interval later), so the steps since
its last checkpoint are lost and must be trained again; then `dgs reconstruct --resume`
finishes it. Both are scored with `dgs eval`; the table puts their held-out scores side by side,
and says whether the two final models are the same to the bit (the checkpoint keeps the random
generator and the view order, so on the same machine they should be).

    python benchmarks/resume.py [--out DIR] [--preset test] [--checkpoint-every 500]
                                [--kill-after 4] [--threads 2] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _reconstruct_cmd(capture: Path, run: Path, preset: str, config: Path) -> list[str]:
    return [sys.executable, "-m", "core.cli", "reconstruct", str(capture), "--out", str(run),
            "--preset", preset, "--config", str(config), "--no-progress"]


def _checkpoint_step(path: Path) -> int:
    import torch

    return int(torch.load(path, map_location="cpu", weights_only=True)["step"])


def run_straight(cmd: list[str], env: dict) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, cwd=ROOT, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def run_killed(cmd: list[str], run: Path, env: dict, kill_after: int) -> tuple[float, int]:
    """Start `cmd`, SIGKILL it half a checkpoint interval after its `kill_after`-th checkpoint,
    then resume it. Returns (seconds in all, the step of the checkpoint it resumed from)."""
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=subprocess.DEVNULL)
    seen: list[float] = []
    last = None
    while len(seen) < kill_after:
        if proc.poll() is not None:
            raise SystemExit(f"the run ended (rc {proc.returncode}) before its {kill_after}-th "
                             "checkpoint; lower --kill-after")
        ckpts = sorted((run / "checkpoints").glob("*.pt")) if (run / "checkpoints").is_dir() else []
        if ckpts:
            stamp = ckpts[0].stat().st_mtime_ns
            if stamp != last:
                last = stamp
                seen.append(time.perf_counter())
        time.sleep(0.05)
    gap = seen[-1] - seen[-2] if len(seen) > 1 else seen[-1] - start
    time.sleep(gap / 2)
    if proc.poll() is not None:
        raise SystemExit("the run ended before the kill; lower --kill-after")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    ckpt = sorted((run / "checkpoints").glob("*.pt"))[0]
    resumed_from = _checkpoint_step(ckpt)
    print(f"killed (SIGKILL) {gap / 2:.0f} s after the checkpoint at step {resumed_from}; "
          "resuming", flush=True)
    subprocess.run(cmd + ["--resume"], check=True, env=env, cwd=ROOT, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start, resumed_from


def _eval(run: Path, env: dict) -> dict:
    subprocess.run([sys.executable, "-m", "core.cli", "eval", str(run)], check=True, env=env,
                   cwd=ROOT, stdout=subprocess.DEVNULL)
    return json.loads((run / "eval.json").read_text())


def _same_model(a: Path, b: Path) -> tuple[bool, float]:
    """(bit-identical, largest absolute difference of any parameter) of two runs' frame PLYs."""
    import torch

    from core.model import GaussianModel

    worst, same = 0.0, True
    for pa in sorted((a / "frames").glob("*/gaussians.ply")):
        pb = b / pa.relative_to(a)
        ma, mb = GaussianModel.load_ply(pa), GaussianModel.load_ply(pb)
        if len(ma) != len(mb):
            return False, float("inf")
        for k, v in ma.params.items():
            d = (v - mb.params[k]).abs().max().item() if v.numel() else 0.0
            worst = max(worst, d)
            same = same and torch.equal(v, mb.params[k])
    return same, worst


def main() -> None:
    from core.demo import DEMO_OVERRIDES, DEMO_SYNTH

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--preset", default="test", help="preset under the overrides (default test, "
                                                     "stretched to the demo's 2500 steps)")
    ap.add_argument("--checkpoint-every", type=int, default=500)
    ap.add_argument("--kill-after", type=int, default=4,
                    help="kill half an interval after this many checkpoints (default 4)")
    ap.add_argument("--threads", type=int, default=2, help="OMP/torch threads of both runs")
    ap.add_argument("--quick", action="store_true",
                    help="the test preset as is on 8 views of 32x32, checkpoints every 100")
    args = ap.parse_args()

    from core.synth import SynthConfig, synthesize

    root = args.out or Path(tempfile.mkdtemp(prefix="dgs-resume-"))
    root.mkdir(parents=True, exist_ok=True)
    synth = dict(DEMO_SYNTH)
    overrides: dict = json.loads(json.dumps(DEMO_OVERRIDES))
    if args.quick:
        synth.update(views=8, width=32, height=32)
        overrides = {}
        args.checkpoint_every, args.kill_after = 100, min(args.kill_after, 3)
    overrides["checkpoint_every"] = args.checkpoint_every
    overrides.setdefault("mesh", {})["enabled"] = False  # meshes are not what this compares
    config = root / "overrides.json"
    config.write_text(json.dumps(overrides, indent=2))
    capture = root / "capture"
    if not (capture / "capture.json").exists():
        synthesize(capture, SynthConfig(**synth))
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    print(f"capture: {synth['views']} views, {synth['width']}x{synth['height']}; preset "
          f"{args.preset} with {config.name}; output in {root}", flush=True)

    straight, killed = root / "straight", root / "killed"
    rows = []
    for name, run in (("left alone", straight), ("killed, then --resume", killed)):
        cmd = _reconstruct_cmd(capture, run, args.preset, config)
        if (run / "metrics.json").is_file():
            seconds, resumed_from = float("nan"), None  # finished earlier: only scored again
        elif run is straight:
            seconds, resumed_from = run_straight(cmd, env), None
        else:
            seconds, resumed_from = run_killed(cmd, run, env, args.kill_after)
        ev = _eval(run, env)
        metrics = json.loads((run / "metrics.json").read_text())
        frame = next(iter(metrics["frames"].values()))
        rows.append({"run": name, "resumed_from": resumed_from, "psnr": ev["psnr"],
                     "psnr_full": ev["psnr_full"], "ssim": ev["ssim"],
                     "normal_cos": ev["normal_cos"], "gaussians": frame["gaussians"],
                     "seconds": seconds})
    same, worst = _same_model(straight, killed)
    print("\n| run | resumed from step | PSNR figure (dB) | PSNR image (dB) | SSIM "
          "| normal cosine | Gaussians | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['run']} | {r['resumed_from'] if r['resumed_from'] is not None else '-'} | "
              f"{r['psnr']:.2f} | {r['psnr_full']:.2f} | {r['ssim']:.4f} | "
              f"{r['normal_cos']:.4f} | {r['gaussians']} | {r['seconds']:.0f} |")
    print(f"\nfinal models bit-identical: {'yes' if same else 'no'} (largest parameter "
          f"difference {worst:.3g})")
    (root / "resume.json").write_text(json.dumps({"rows": rows, "identical": same,
                                                  "max_param_diff": worst}, indent=2))


if __name__ == "__main__":
    main()
