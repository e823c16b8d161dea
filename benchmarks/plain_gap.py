"""Why the old "plain 3DGS" trailed a real one (issue 30): a plain 3DGS (`train.method` 3dgs,
the reference 3DGS's and gsplat DefaultStrategy's densification and classic rasterization) with
one of the method's own choices put back at a time, on a real capture, same views, seeds and
steps (`benchmarks/real.py` trains and scores each).

- `3dgs`: the plain 3DGS;
- `+absgrad`: AbsGS's statistic (absolute gradients, threshold 0.0008) instead of 3DGS's mean
  gradient above 0.0002;
- `+revised`: clones and splits share the opacity (Bulo et al. 2024) instead of keeping it;
- `+prune-at-reset`: transparent Gaussians pruned only at opacity resets, not at every
  densification;
- `+rho`: the lowest-contribution 10% pruned at each reset;
- `+mip`: the Mip-Splatting 2D filter (0.1 px, opacity compensation) instead of 3DGS's 0.3;
- `old`: every one of them: the appearance-only mode the benchmarks called plain 3DGS before
  2026-11-27;
- `no-reset`: no opacity resets (the reset steps still start the too-big pruning): what released
  gsplat 1.5.3's `DefaultStrategy` does, its reset condition never holding (gsplat pull request
  776 fixed it after that release), so the 3DGS gsplat 1.5.3 trains, on our trainer.

    nice python benchmarks/plain_gap.py CAPTURE --out DIR [--downscale 8] [--preset fast]
                                        [--variants 3dgs old ...] [--seed 0] [--threads 1]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.real import run_variant  # noqa: E402

# Each of the method's choices, as train settings over a plain 3DGS's.
CHOICES: dict[str, dict] = {
    "+absgrad": {"densify": {"gradient": "absolute", "grad_threshold_c": 0.0008}},
    "+revised": {"densify": {"revised_opacity": True}},
    "+prune-at-reset": {"densify": {"prune_at": "reset"}},
    "+rho": {"densify": {"rho": 0.1}},
    "+mip": {"eps2d": 0.1, "antialiased": True},
}
# Not one of the method's choices: a plain 3DGS as gsplat 1.5.3 trains it (module docstring).
GSPLAT_153 = {"densify": {"reset_opacity": False}}


def settings(variant: str) -> dict:
    """The train settings of `variant` over the plain 3DGS's."""
    if variant == "3dgs":
        return {}
    if variant == "no-reset":
        return GSPLAT_153
    parts = list(CHOICES) if variant == "old" else [variant]
    out: dict = {}
    for part in parts:
        for key, value in CHOICES[part].items():
            out[key] = {**out.get(key, {}), **value} if isinstance(value, dict) else value
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--downscale", type=float, default=8.0)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--variants", nargs="+", default=["3dgs", *CHOICES, "old"],
                    choices=["3dgs", *CHOICES, "old", "no-reset"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args()
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    rows = []
    for variant in args.variants:
        out = args.out / f"{variant.lstrip('+')}-s{args.seed}"
        row = run_variant(args.capture, out, "plain", args.preset, args.downscale, args.steps,
                          seed=args.seed, extra=settings(variant))
        row["variant"] = variant
        rows.append(row)
        (args.out / f"{variant.lstrip('+')}-s{args.seed}.json").write_text(
            json.dumps(row, indent=2))
    print(f"\n{args.capture} at 1/{args.downscale:g}, preset {args.preset}, seed {args.seed}\n")
    print("| variant | held-out PSNR | SSIM | train PSNR | Gaussians | s |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['variant']} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['train_psnr']:.2f} | "
              f"{r['gaussians']} | {r['seconds']:.0f} |")


if __name__ == "__main__":
    main()
