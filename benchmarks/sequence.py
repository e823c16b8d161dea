"""Sequential (deform + refine inside GoPs) against independent per-frame reconstruction at the
same total iteration budget, on a `dgs synth` sequence; plus two ablations of the sequential
method: without the temporal L1 and without the anisotropy loss.

Variants (same capture, same key-frame schedule):
- sequential: GoPs of --gop frames; key frames get K steps, the others deform + refine;
- independent: every frame a key frame with the static stages scaled to total / frames steps,
  where total is the sequential run's total count of rendered training images (equal budget:
  a deform step that averages k views costs k);
- independent-3dgs: the same with a plain 3DGS per frame (`train.method` 3dgs, docs/design.md
  5.14.1), what a 3DGS user without a sequence method would run;
- no-temporal, no-anisotropy: sequential with that loss off.
Reported: held-out PSNR (figure pixels) and normal cosine (against ground truth), flicker of the
normal and AO maps (core.sequence.metrics), the largest PSNR drop between consecutive frames of
a group, the track error (how far tracked Gaussians are from the body points they were born
on, core.sequence.correspondence), Gaussians per frame, seconds per key frame and per other frame.
Results go to OUT/results.json (updated after each variant; finished variants are reused).

    python benchmarks/sequence.py [--quick] [--frames 24] [--views 16] [--size 64]
                                  [--iterations 500] [--gop 20] [--out DIR]
                                  [--subject CHARACTER.glb [--fps 24]]

`--subject` films a skinned glTF character instead of the built-in figure (`dgs synth
--subject`), e.g. ../shared/data/animated/CesiumMan.glb when that folder exists.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

VARIANTS = ("sequential", "independent", "independent-3dgs", "no-temporal", "no-anisotropy")
# The group-boundary study (issue 22): the refine budget drawn on the whole run instead of
# each group, and key frames trained for key_steps x the schedule (the default is 2: key-1 is
# the plain schedule, as before 2026-11-26).
STUDY = ("run-budget", "key-1", "key-1.5", "key-2")


def _schedule(iterations: int) -> dict:
    from core.config import schedule_for

    return asdict(schedule_for("paper").scaled(iterations))


def overrides(variant: str, iterations: int, total: int | None, frames: int, gop: int,
              train_seed: int = 0) -> dict:
    """The run's configuration overrides for `variant` (`total`: the sequential run's rendered
    training images)."""
    base = {"gop": gop, "checkpoint_every": 100_000,
            "train": {"schedule": _schedule(iterations), "init_points": 2_000,
                      "seed": train_seed}}
    if variant in ("independent", "independent-3dgs"):
        per_frame = max(3, round(total / frames))
        base["train"]["schedule"] = _schedule(per_frame)
        base["sequence"] = {"enabled": False}
        if variant == "independent-3dgs":
            base["train"]["method"] = "3dgs"
    elif variant == "run-budget":
        base.setdefault("sequence", {})["refine_scope"] = "run"
    elif variant.startswith("key-"):
        base.setdefault("sequence", {})["key_steps"] = float(variant[4:])
    elif variant == "no-temporal":
        base.setdefault("sequence", {})["temporal"] = False
    elif variant == "no-anisotropy":
        base.setdefault("sequence", {})["anisotropy"] = 0.0
    return base


def summarize(run: Path) -> dict:
    """The row of one finished run."""
    from core.evaluation import evaluate_run

    ev = evaluate_run(run)
    seq = json.loads((run / "sequence.json").read_text())
    metrics = json.loads((run / "metrics.json").read_text())["frames"]
    t = ev["temporal"]
    return {"psnr": ev["psnr"], "normal_cos": ev["normal_cos"], "flicker": t["flicker"],
            "flicker_normal": t["flicker_normal"], "flicker_ao": t["flicker_ao"],
            "largest_drop_db": t["largest_psnr_drop_in_group"],
            "boundaries": t.get("boundaries"),
            "track_error": t.get("track_error"), "track_error_mm": t.get("track_error_mm"),
            "gaussians_per_frame": seq["gaussians"]["mean"],
            "seconds_per_frame": round(seq["timings"]["seconds_total"] / len(metrics), 2),
            "seconds_key": seq["timings"]["seconds_per_key_frame"],
            "seconds_other": seq["timings"]["seconds_per_deformed_frame"],
            "steps_total": sum(m["iterations"] for m in metrics.values()),
            "renders_total": sum(m.get("renders", m["iterations"]) for m in metrics.values()),
            # Across group boundaries too.
            "largest_drop_any_db": max((a - b for a, b in zip(t["psnr_per_frame"],
                                                              t["psnr_per_frame"][1:])),
                                       default=None),
            "psnr_per_frame": [round(p, 2) for p in t["psnr_per_frame"]]}


def _track(row: dict) -> str:
    """The track error cell: % of the diagonal (mm); '-' for independent frames (no tracks)."""
    if row.get("track_error") is None:
        return "-"
    return f"{row['track_error']:.2f} ({row['track_error_mm']:.0f})"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="24 frames, 16 views, 48x48, 300 steps per key frame")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--iterations", type=int, default=500, help="steps per key frame")
    ap.add_argument("--gop", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--train-seed", type=int, default=0, help="training seed (TrainConfig.seed)")
    ap.add_argument("--subject", default="",
                    help="a skinned glTF 2.0 character (.glb) to film instead of the figure")
    ap.add_argument("--fps", type=float, default=24.0,
                    help="frames per second of the character's animation")
    ap.add_argument("--out", default="/tmp/dgs-bench-sequence")
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.iterations = 48, 300
    import torch

    from core.pipeline import reconstruct
    from core.synth import SynthConfig, synthesize

    torch.set_num_threads(max(1, torch.get_num_threads()))
    out = Path(args.out)
    capture = out / "capture"
    if not (capture / "capture.json").is_file():
        if args.subject and not Path(args.subject).is_file():
            raise SystemExit(f"--subject: {args.subject} not found (the shared data folder "
                             "holds CesiumMan.glb under animated/)")
        synthesize(capture, SynthConfig(frames=args.frames, views=args.views, width=args.size,
                                        height=args.size, seed=args.seed, priors=True,
                                        subject=args.subject, fps=args.fps))
    results_path = out / "results.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else {}
    results["setup"] = {k: getattr(args, k) for k in ("frames", "views", "size", "iterations",
                                                       "gop", "seed", "train_seed",
                                                       "subject", "fps")}
    total = None
    for variant in args.variants.split(","):
        run = out / variant
        if variant != "sequential" and total is None:
            total = results.get("sequential", {}).get("renders_total")
            if total is None:
                raise SystemExit("run the sequential variant first (its rendered images are the budget)")
        if variant in results and (run / "eval.json").is_file():
            continue
        start = time.perf_counter()
        reconstruct(capture, run, preset="test", resume=(run / "config.json").is_file(),
                    overrides=overrides(variant, args.iterations, total, args.frames, args.gop,
                                        args.train_seed),
                    progress=False)
        row = summarize(run)
        row["wall_s"] = round(time.perf_counter() - start, 1)
        results[variant] = row
        if variant == "sequential":
            total = row["renders_total"]
        results_path.write_text(json.dumps(results, indent=2) + "\n")
        print(variant, json.dumps({k: v for k, v in row.items() if k != "psnr_per_frame"}),
              flush=True)
    print("| variant | PSNR | normal cos | flicker (normal / AO) | largest drop in GoP (dB) | "
          "track error (% diag., mm) | Gaussians / frame | s / frame (key / other) | renders |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for v in (*VARIANTS, *STUDY):
        r = results.get(v)
        if r:
            drop = r["largest_drop_db"]
            renders = r.get("renders_total", r["steps_total"])
            print(f"| {v} | {r['psnr']:.2f} | {r['normal_cos']:.3f} | {r['flicker']:.4f} "
                  f"({r['flicker_normal']:.4f} / {r['flicker_ao']:.4f}) | "
                  f"{drop if drop is None else round(drop, 2)} | "
                  f"{_track(r)} | {r['gaussians_per_frame']:.0f} | {r['seconds_per_frame']:.1f} "
                  f"({r['seconds_key']} / {r['seconds_other']}) | {renders} |")
    print("\n| variant | groups' boundaries | largest drop into a key frame (dB) | "
          "largest drop inside (dB) | flicker at boundaries / inside |")
    print("| --- | --- | --- | --- | --- |")
    for v in (*VARIANTS, *STUDY):
        b = (results.get(v) or {}).get("boundaries")
        if b and b["count"]:
            r = results[v]
            inside = r["largest_drop_db"]  # None: no group has two frames
            ratio = b["flicker_ratio"]
            print(f"| {v} | {b['count']} | {b['largest_psnr_drop']:.2f} | "
                  f"{'-' if inside is None else f'{inside:.2f}'} | {b['flicker']:.4f} / "
                  f"{b['flicker_inside'] or 0:.4f} ({'-' if ratio is None else f'{ratio:.2f}'}x) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
