"""Seconds per CPU training step at equal Gaussians, by image size and thread count (issue 23).

One model (a checkpoint or a Gaussian PLY) rendered from one training camera of its capture and
trained one step (render, L1 + D-SSIM, backward, Adam step), in stage 1 (appearance only, a
plain 3DGS step) and stage 3 (both branches, every loss of the method), at each downscale and
thread count asked for. Median of `--repeats` steps after two warm-up steps; the columns of one
row share the process, so compare within a row.

    python benchmarks/step.py MODEL CAPTURE [--downscales 8 4] [--threads 1 2] [--repeats 7]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from ao import load_model  # noqa: E402


def step_seconds(model, view, stage: int, repeats: int) -> float:
    from core.config import train_config
    from core.training import Trainer

    cfg = replace(train_config("fast"), bake_ao=False)
    trainer = Trainer([view], cfg, model=model)
    sched = cfg.schedule
    trainer.step = {1: 0, 3: sched.stage3_start + 1}[stage]
    times = []
    for i in range(repeats + 2):
        start = time.perf_counter()
        terms, _, _ = trainer.step_terms(0, trainer.background)
        sum(terms.values()).backward()
        trainer.optimizer.step()
        trainer.optimizer.zero_grad(set_to_none=True)
        if i >= 2:
            times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("model", type=Path)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--downscales", type=float, nargs="+", default=[8.0, 4.0])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    from core.data import load_capture
    from core.data.dataset import CaptureDataset
    from core.training import View

    cap = load_capture(args.capture)
    base = load_model(args.model)
    print(f"{len(base)} Gaussians; seconds per step (median of {args.repeats})\n")
    cols = [f"stage {s}, {t} thr" for s in (1, 3) for t in args.threads]
    print("| image | " + " | ".join(cols) + " |\n" + "|---" * (len(cols) + 1) + "|")
    for ds in args.downscales:
        sample = CaptureDataset(cap, frames=cap.frames[:1], cameras=[cap.cameras[1].id],
                                downscale=ds)[0]
        view = View.from_sample(sample)
        row = []
        for stage in (1, 3):
            for threads in args.threads:
                torch.set_num_threads(threads)
                model = type(base)({k: v.clone() for k, v in base.params.items()})
                row.append(step_seconds(model, view, stage, args.repeats))
        print(f"| {view.camera.width}x{view.camera.height} | "
              + " | ".join(f"{s:.3f}" for s in row) + " |", flush=True)


if __name__ == "__main__":
    main()
