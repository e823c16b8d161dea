"""Ablation of the disentangled method on one synthetic capture at one budget.

Variants (same preset, same capture, same number of iterations):
- disentangled: the method (beta annealed from 0 to 0.7 over stages 2 and 3);
- merged: beta = 0 throughout, so both branches blend with the same (averaged) opacity;
- appearance-only: plain 3DGS (stage 1 for the whole budget); its normals are each Gaussian's
  shortest axis, blended with the appearance opacity, as usual for 3DGS.
Held-out PSNR (figure pixels and whole image) / SSIM against the capture and normal cosine
against the ground-truth normals. With --out an existing capture and finished variants there are
reused (a run directory with eval.json is scored again, not trained again).

    python benchmarks/ablation.py [--preset fast] [--views 16] [--size 128] [--seed 0]
                                  [--out DIR] [--quick]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

VARIANTS = ("disentangled", "merged", "appearance-only")


def _overrides(variant: str, iterations: int) -> dict:
    if variant == "merged":
        return {"train": {"schedule": {"beta_max": 0.0}}}
    if variant == "appearance-only":
        return {"train": {"schedule": {"stage2_start": iterations, "stage3_start": iterations}}}
    return {}


def _appearance_normals(capture_dir: Path, run: Path, preset: str) -> None:
    """Give a plain 3DGS model the usual normals (shortest axes, appearance opacity) and render
    its held-out views again."""
    import torch

    from core.data import load_capture
    from core.model import GaussianModel
    from core.pipeline import render_heldout
    from core.render import RenderCamera
    from core.config import train_config

    capture = load_capture(capture_dir)
    centers = torch.stack([RenderCamera.from_camera(c).center for c in capture.cameras])
    for ply in sorted((run / "frames").glob("*/gaussians.ply")):
        frame = ply.parent.name
        model = GaussianModel.load_ply(ply)
        model.init_geometry(centers)  # normals = shortest axes; opacity_g = opacity_c
        model.assign("visibility", torch.full_like(model.params["visibility"], 9.0))
        stand_in = SimpleNamespace(model=model, config=train_config(preset))
        render_heldout(capture, frame, stand_in, run / "renders" / frame)


def run_variant(capture: Path, out: Path, variant: str, preset: str) -> dict:
    from core.evaluation import evaluate_run
    from core.pipeline import reconstruct
    from core.config import train_config

    iterations = train_config(preset).schedule.iterations
    if (out / "eval.json").is_file() and (out / "metrics.json").is_file():
        metrics = json.loads((out / "metrics.json").read_text())  # finished earlier: reuse
    else:  # resume: an interrupted variant continues from its checkpoint
        metrics = reconstruct(capture, out, preset=preset, resume=True,
                              overrides=_overrides(variant, iterations), progress=False)
        if variant == "appearance-only":
            _appearance_normals(capture, out, preset)
    ev = evaluate_run(out)
    frame = next(iter(metrics["frames"].values()))
    return {"variant": variant, "psnr": ev["psnr"], "psnr_full": ev["psnr_full"],
            "ssim": ev["ssim"], "normal_cos": ev["normal_cos"], "normal_deg": ev["normal_deg"],
            "gaussians": frame["gaussians"], "seconds": frame["seconds"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--seed", type=int, default=0, help="dgs synth seed of the capture")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--quick", action="store_true", help="test preset, 8 views of 32x32")
    args = ap.parse_args()
    if args.quick:
        args.preset, args.views, args.size = "test", 8, 32
    from core.synth import SynthConfig, synthesize

    root = args.out or Path(tempfile.mkdtemp(prefix="dgs-ablation-"))
    capture = root / "capture"
    if not (capture / "capture.json").exists():
        synthesize(capture, SynthConfig(frames=1, views=args.views, width=args.size,
                                        height=args.size, seed=args.seed, priors=True))
    print(f"capture: {args.views} views, {args.size}x{args.size}, seed {args.seed}, preset "
          f"{args.preset}, output in {root}\n")
    print("| variant | PSNR figure (dB) | PSNR image (dB) | SSIM | normal cosine "
          "| normal error (deg) | Gaussians | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for variant in VARIANTS:
        r = run_variant(capture, root / variant, variant, args.preset)
        rows.append(r)
        fmt = lambda v, f: "n/a" if v is None else format(v, f)  # noqa: E731
        print(f"| {variant} | {fmt(r['psnr'], '.2f')} | {fmt(r['psnr_full'], '.2f')} | "
              f"{fmt(r['ssim'], '.4f')} | "
              f"{fmt(r['normal_cos'], '.4f')} | {fmt(r['normal_deg'], '.1f')} | "
              f"{fmt(r['gaussians'], 'd')} | {r['seconds']:.0f} |", flush=True)
    (root / "ablation.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
