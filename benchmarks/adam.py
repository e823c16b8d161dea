"""The optimizer step alone: torch's default Adam against its fused one, at a model's layout.

`GaussianModel.make_optimizer` gives Adam one group per parameter (means, quaternions, scales,
both opacities, normals, visibility, SH): torch's default runs about ten operators a group (on
the CPU a loop over the group's tensors, on a GPU ten kernel launches), the fused one a single
kernel a group. Both are timed in one process on the same parameters and gradients, for each
model size; the last column is their ratio. The updates agree to float rounding (a test).

With `--model MODEL --capture CAPTURE` (a checkpoint or PLY and its capture), a whole stage-3
training step on one view (render, every loss, backward; then the optimizer) is timed too, both
ways in turn, so the optimizer's share of a step shows.

    python benchmarks/adam.py [--gaussians 60000 300000 1000000] [--threads 1] [--repeats 9]
                              [--device cpu|cuda] [--model MODEL --capture CAPTURE]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # ao.load_model


def as_default(optimizer: torch.optim.Adam) -> None:
    """Make a fused Adam run torch's default implementation, as `make_optimizer`'s did before
    2026-12-01 (before its first step: nothing else differs)."""
    for group in optimizer.param_groups:
        group["fused"] = None


def step_ms(model, fused: bool, repeats: int, device: torch.device) -> float:
    """Median milliseconds of one optimizer step (after two warm-ups)."""
    from core.config import LearningRates

    optimizer = model.make_optimizer(LearningRates())
    if not fused:
        as_default(optimizer)
    gen = torch.Generator().manual_seed(0)
    for p in model.params.values():
        p.grad = torch.randn(p.shape, generator=gen).to(device)
    times = []
    for i in range(repeats + 2):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        optimizer.step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        if i >= 2:
            times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def training_step_ms(base, capture, repeats: int) -> list[tuple[str, float, float]]:
    """(optimizer, forward and backward ms, optimizer ms), medians, each way twice in turn."""
    from dataclasses import replace

    from core.config import train_config
    from core.data import load_capture
    from core.data.dataset import CaptureDataset
    from core.training import Trainer, View

    cap = load_capture(capture)
    view = View.from_sample(CaptureDataset(cap, frames=cap.frames[:1],
                                           cameras=[cap.cameras[1].id])[0])
    cfg = replace(train_config("fast"), bake_ao=False)
    rows = []
    for fused in (False, True, False, True):
        trainer = Trainer([view], cfg, model=type(base)({k: v.clone()
                                                          for k, v in base.params.items()}))
        if not fused:
            as_default(trainer.optimizer)
        trainer.step = cfg.schedule.stage3_start + 1
        passes, steps = [], []
        for i in range(repeats + 2):
            start = time.perf_counter()
            terms, _, _ = trainer.step_terms(0, trainer.background)
            sum(terms.values()).backward()
            middle = time.perf_counter()
            trainer.optimizer.step()
            trainer.optimizer.zero_grad(set_to_none=True)
            if i >= 2:
                passes.append(middle - start)
                steps.append(time.perf_counter() - middle)
        rows.append(("fused" if fused else "default", 1e3 * statistics.median(passes),
                     1e3 * statistics.median(steps)))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, nargs="+", default=[60_000, 300_000, 1_000_000])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--model", type=Path, default=None)
    ap.add_argument("--capture", type=Path, default=None)
    args = ap.parse_args(argv)
    if (args.model is None) != (args.capture is None):
        ap.error("--model and --capture go together")
    torch.set_num_threads(args.threads)
    from core.device import resolve_device
    from core.model import GaussianModel

    device = resolve_device(args.device)
    print(f"Adam step, ms (median of {args.repeats}), {device.type}, {args.threads} thread(s)\n")
    print("| Gaussians | default | fused | default / fused |\n|---|---|---|---|")
    for n in args.gaussians:
        gen = torch.Generator().manual_seed(1)
        points = torch.rand(n, 3, generator=gen)
        model = GaussianModel.from_points(points.to(device))
        model.init_geometry(torch.zeros(1, 3, device=device))  # both branches' parameters
        row = [step_ms(model, fused, args.repeats, device) for fused in (False, True)]
        print(f"| {n:,} | {row[0]:.1f} | {row[1]:.1f} | {row[0] / row[1]:.2f}x |", flush=True)
    if args.model is not None:
        from ao import load_model

        base = load_model(args.model)
        print(f"\na stage-3 training step, {len(base):,} Gaussians, ms (median of "
              f"{args.repeats})\n")
        print("| Adam | render, losses, backward | optimizer | optimizer's share |")
        print("|---|---|---|---|")
        for name, passes, step in training_step_ms(base, args.capture, args.repeats):
            print(f"| {name} | {passes:.0f} | {step:.1f} | {step / (passes + step):.0%} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
