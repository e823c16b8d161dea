"""A real capture, our method beside a plain 3DGS on the same images, views, seeds and steps
(issue 23).

- method: `dgs reconstruct` with the preset (disentangled stages, AO bake, every loss);
- plain 3DGS: the same trainer as a plain 3D Gaussian Splatting (`train.method` 3dgs: one
  opacity, photometric loss only, no geometry branch, no AO, the SH degree raised every
  `sh_interval` steps from the start, 3DGS's densification and classic rasterization), with
  the same initial points.
Both from the same capture at the same downscale, then `dgs eval` (held-out views, every 8th
camera): PSNR over the whole image and SSIM, and over the subject where the capture has masks
(`benchmarks/subject_masks.py` makes a masked capture). Meshes are skipped unless `--mesh`
(the method's: a plain 3DGS has no geometry branch). `--steps N` scales the preset's plan to N
steps (`Schedule.scaled`: every boundary in proportion). `--set KEY=VALUE` lays a setting of the run's
config over both variants' (dotted, VALUE JSON, as `benchmarks/panoptic.py` takes it: e.g.
`--set train.init.source=triangulate` seeds from sparse points where the default fuses stereo).

    nice python benchmarks/real.py CAPTURE --out DIR [--downscale 4] [--preset fast]
                                   [--steps N] [--mesh] [--variants method plain] [--threads 1]
                                   [--seed S] [--set KEY=VALUE ...]

Finished variants in DIR are scored again, not trained again; an interrupted one resumes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.panoptic import lay_setting  # noqa: E402

VARIANTS = ("method", "plain")


def overrides(variant: str, preset: str, downscale: float, steps: int | None = None,
              mesh: bool = False, seed: int = 0, settings: tuple[str, ...] = ()) -> dict:
    from dataclasses import asdict

    from core.config import train_config

    s = train_config(preset).schedule
    if steps is not None:
        s = s.scaled(steps)
    out = {"downscale": downscale, "mesh": {"enabled": mesh and variant == "method"},
           "train": {"schedule": asdict(s), "seed": seed}}
    if steps is not None:
        out["train"]["rates"] = {"means_decay_steps": steps}
    if variant == "plain":
        out["train"]["method"] = "3dgs"
    for setting in settings:
        lay_setting(out, setting)
    return out


def run_variant(capture: Path, out: Path, variant: str, preset: str, downscale: float,
                steps: int | None = None, mesh: bool = False, seed: int = 0,
                extra: dict | None = None, settings: tuple[str, ...] = ()) -> dict:
    """Train (or resume, or re-score) one variant in `out`; `extra` train settings are laid
    over the variant's (`benchmarks/plain_gap.py`)."""
    from core.data import load_capture
    from core.evaluation import evaluate_run
    from core.pipeline import reconstruct

    done = (out / "metrics.json").is_file() and not any((out / "checkpoints").glob("*.pt"))
    if done:
        metrics = json.loads((out / "metrics.json").read_text())
    else:
        over = overrides(variant, preset, downscale, steps, mesh, seed, settings)
        over["train"].update(extra or {})
        metrics = reconstruct(capture, out, preset=preset, resume=True, progress=True,
                              overrides=over)
    ev = evaluate_run(out)
    frame = next(iter(metrics["frames"].values()))
    steps = frame["iterations"]
    cap = load_capture(capture)
    masked = any(cap.mask_path(f, c.id) for f in cap.frames for c in cap.cameras)
    return {"variant": variant, "seed": seed, "psnr": ev["psnr_full"], "ssim": ev["ssim"],
            "psnr_subject": ev["psnr"] if masked else None, "normal_deg": ev["normal_deg"],
            "train_psnr": frame["train_psnr"], "gaussians": frame["gaussians"],
            "seconds": frame["seconds"], "ao_bake_seconds": frame.get("ao_bake_seconds"),
            "s_per_step": frame["seconds"] / steps, "seeds": frame["notes"][0]
            if frame["notes"] else ""}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--steps", type=int, default=None, help="the preset's plan scaled to N steps")
    ap.add_argument("--mesh", action="store_true", help="mesh the method's frame")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: all)")
    ap.add_argument("--seed", type=int, default=0, help="train.seed (view order, splits)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a setting of the run's config, dotted, VALUE JSON (e.g. "
                         "train.init.source=triangulate)")
    args = ap.parse_args()
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    rows = []
    for variant in args.variants:
        rows.append(run_variant(args.capture, args.out / variant, variant, args.preset,
                                args.downscale, args.steps, args.mesh, args.seed,
                                settings=tuple(args.set)))
        (args.out / f"{variant}.json").write_text(json.dumps(rows[-1], indent=2))
    steps = f", {args.steps} steps" if args.steps else ""
    print(f"\n{args.capture} at 1/{args.downscale:g}, preset {args.preset}{steps}\n")
    print("| variant | held-out PSNR | subject PSNR | SSIM | normals (deg) | train PSNR | "
          "Gaussians | s | s/step | AO bake s (share) |")
    print("|---|---|---|---|---|---|---|---|---|---|")

    def num(v, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    for r in rows:
        bake = "-" if r["ao_bake_seconds"] is None else \
            f"{r['ao_bake_seconds']:.0f} ({r['ao_bake_seconds'] / r['seconds']:.1%})"
        print(f"| {r['variant']} | {r['psnr']:.2f} | {num(r['psnr_subject'], '.2f')} | "
              f"{r['ssim']:.4f} | {num(r['normal_deg'], '.1f')} | {r['train_psnr']:.2f} | "
              f"{r['gaussians']} | {r['seconds']:.0f} | {r['s_per_step']:.3f} | {bake} |")
    for r in rows:
        print(f"- {r['variant']}: {r['seeds']}")


if __name__ == "__main__":
    main()
