"""Ablation of the disentangled method on one synthetic capture at one budget.

Variants (same preset, same capture, same number of iterations):
- disentangled: the method (beta annealed from 0 to 0.7 over stages 2 and 3);
- merged: beta = 0 throughout, so both branches blend with the same (averaged) opacity;
- 3dgs: a plain 3D Gaussian Splatting (`train.method` 3dgs, docs/design.md 5.14.1): one
  opacity, the photometric loss, 3DGS's densification and rates; its normals are each Gaussian's
  shortest axis, blended with its one opacity, as a 3DGS user reads them off.
Held-out PSNR (figure pixels and whole image) / SSIM against the capture and normal cosine
against the ground-truth normals, one row per run and, with several `--train-seeds`, the mean
and range per variant. With --out an existing capture and finished runs there are reused (a run
directory with eval.json is scored again, not trained again).

    python benchmarks/ablation.py [--preset fast] [--views 16] [--size 128] [--seed 0]
                                  [--variants ...] [--train-seeds 0 1 2] [--out DIR] [--quick]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

VARIANTS = ("disentangled", "merged", "3dgs")


def _overrides(variant: str, seed: int) -> dict:
    train: dict = {"seed": seed}
    if variant == "merged":
        train["schedule"] = {"beta_max": 0.0}
    if variant == "3dgs":
        train["method"] = "3dgs"
    return {"train": train}


def run_variant(capture: Path, out: Path, variant: str, preset: str, seed: int) -> dict:
    from core.evaluation import evaluate_run
    from core.pipeline import reconstruct

    if (out / "eval.json").is_file() and (out / "metrics.json").is_file():
        metrics = json.loads((out / "metrics.json").read_text())  # finished earlier: reuse
    else:  # resume: an interrupted variant continues from its checkpoint
        metrics = reconstruct(capture, out, preset=preset, resume=True,
                              overrides=_overrides(variant, seed), progress=False)
    ev = evaluate_run(out)
    frame = next(iter(metrics["frames"].values()))
    return {"variant": variant, "seed": seed, "psnr": ev["psnr"], "psnr_full": ev["psnr_full"],
            "ssim": ev["ssim"], "normal_cos": ev["normal_cos"], "normal_deg": ev["normal_deg"],
            "gaussians": frame["gaussians"], "seconds": frame["seconds"]}


def _spread(runs: list[dict], key: str, spec: str = ".2f", extent: bool = True) -> str:
    """The mean of `key` over `runs` and, with `extent`, its range over the runs that have it;
    a bare mean is n/a when a run lacks it (n/a too when none has it)."""
    values = [r[key] for r in runs if r[key] is not None]
    if not values or (not extent and len(values) < len(runs)):
        return "n/a"
    mean = format(sum(values) / len(values), spec)
    return f"{mean} ({min(values):{spec}}-{max(values):{spec}})" if extent else mean


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--seed", type=int, default=0, help="dgs synth seed of the capture")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    ap.add_argument("--train-seeds", nargs="+", type=int, default=[0],
                    help="training seeds (train.seed): one run per variant and seed")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--quick", action="store_true", help="test preset, 8 views of 32x32")
    args = ap.parse_args()
    if args.quick:
        args.preset, args.views, args.size = "test", 8, 32
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    from core.synth import SynthConfig, synthesize

    root = args.out or Path(tempfile.mkdtemp(prefix="dgs-ablation-"))
    capture = root / "capture"
    if not (capture / "capture.json").exists():
        synthesize(capture, SynthConfig(frames=1, views=args.views, width=args.size,
                                        height=args.size, seed=args.seed, priors=True))
    print(f"capture: {args.views} views, {args.size}x{args.size}, seed {args.seed}, preset "
          f"{args.preset}, output in {root}\n")
    print("| variant | seed | PSNR figure (dB) | PSNR image (dB) | SSIM | normal cosine "
          "| normal error (deg) | Gaussians | seconds |")
    print("|---|---|---|---|---|---|---|---|---|")
    rows = []
    fmt = lambda v, f: "n/a" if v is None else format(v, f)  # noqa: E731
    for seed in args.train_seeds:  # seeds outermost: every variant has a row before the next
        for variant in args.variants:
            name = variant if seed == 0 else f"{variant}-s{seed}"  # seed 0 keeps its old folder
            r = run_variant(capture, root / name, variant, args.preset, seed)
            rows.append(r)
            print(f"| {variant} | {seed} | {fmt(r['psnr'], '.2f')} | "
                  f"{fmt(r['psnr_full'], '.2f')} | {fmt(r['ssim'], '.4f')} | "
                  f"{fmt(r['normal_cos'], '.4f')} | {fmt(r['normal_deg'], '.1f')} | "
                  f"{fmt(r['gaussians'], 'd')} | {r['seconds']:.0f} |", flush=True)
            (root / "ablation.json").write_text(json.dumps(rows, indent=2))
    if len(args.train_seeds) > 1:
        print("\n| variant | runs | PSNR figure mean (range) | PSNR image mean (range) "
              "| SSIM mean | normal cosine mean |")
        print("|---|---|---|---|---|---|")
        for variant in args.variants:
            runs = [r for r in rows if r["variant"] == variant]
            print(f"| {variant} | {len(runs)} | {_spread(runs, 'psnr')} | "
                  f"{_spread(runs, 'psnr_full')} | {_spread(runs, 'ssim', '.4f', False)} | "
                  f"{_spread(runs, 'normal_cos', '.4f', False)} |")


if __name__ == "__main__":
    main()
