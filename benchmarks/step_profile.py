"""Per-step work of a key frame and a tracked frame (issue 38, "fast enough to fit"): device
operations and host synchronisations a step issues, counted with torch.profiler, and where each
synchronisation comes from.

On a GPU every operator is a kernel launch (or more) and every read of a device value on the
host (`.item()`, `float()`, `bool()`, `.tolist()`, `.cpu()`, `.numpy()`, `nonzero`, indexing
with a boolean mask) stalls the launch queue until the device catches up; on the CPU both cost
next to nothing, so a loop written on the CPU hides them. This counts them per step:

- ops: leaf aten operators (no aten operator below them) and our rasterizer's ops, per step:
  about one kernel launch each on CUDA (view and metadata operators excluded); with CUDA the
  launches the profiler sees are counted too;
- syncs: reads of device values on the host (and tensors made from host data), by kind and by
  the line that asks; reads that stay on the host on a GPU too (`HOST_ONLY`) counted apart.

A tiny synthetic capture (64x64, 8 views, subject masks so a tracked frame moves a subset):
the key frame's stage-3 step (every term of the method), and a tracked frame's deform and
refine steps. Counts depend on the code path, not on the image size.

    python benchmarks/step_profile.py [--device cpu|cuda] [--steps 20] [--label NAME]
        [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from core.syncs import SyncCounter  # noqa: E402

VIEW_OPS = {"aten::view", "aten::_unsafe_view", "aten::as_strided", "aten::t",
            "aten::transpose", "aten::permute", "aten::expand", "aten::select", "aten::slice",
            "aten::unsqueeze", "aten::squeeze", "aten::alias", "aten::detach", "aten::reshape",
            "aten::unbind", "aten::split", "aten::chunk", "aten::narrow", "aten::view_as",
            "aten::expand_as", "aten::lift_fresh", "aten::empty", "aten::empty_strided",
            "aten::resolve_conj", "aten::resolve_neg", "aten::result_type", "aten::size",
            "aten::stride", "aten::is_nonzero", "aten::empty_like", "aten::zeros_like_meta"}


def profile(step, steps: int, device: torch.device) -> dict:
    """Ops, launches and syncs per step of `step()` over `steps` calls (after two warm-ups)."""
    for _ in range(2):
        step()
    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
        torch.cuda.synchronize()
    counter = SyncCounter()
    with torch.profiler.profile(activities=activities) as prof, counter:
        for _ in range(steps):
            step()
        if device.type == "cuda":
            torch.cuda.synchronize()
    events = prof.events()
    ops = launches = scalar_reads = 0
    for e in events:
        name = e.name
        if name.startswith("cudaLaunchKernel") or name.startswith("cuLaunchKernel"):
            launches += 1
        if name == "aten::_local_scalar_dense":
            scalar_reads += 1
        aten_below = any(c.name.startswith(("aten::", "dgs::")) for c in e.cpu_children)
        if name.startswith(("aten::", "dgs::")) and name not in VIEW_OPS and not aten_below:
            ops += 1
    return {"ops": ops / steps, "launches": launches / steps if launches else None,
            "scalar_reads": scalar_reads / steps, "host_only": counter.host_only / steps,
            "syncs": counter.syncs / steps,
            "sync_kinds": {k: v / steps for k, v in counter.by_kind.most_common()},
            "sync_lines": {k: v / steps for k, v in counter.by_line.most_common(12)}}


def build(tmp: Path, device: str, key_steps: int = 240):
    """A key-frame trainer at its stage 3 and a tracked frame's fitter after it (the key frame
    trained `key_steps` first: a model to track)."""
    from core.config import SequenceConfig, select_views, train_config
    from core.data import load_capture
    from core.sequence import FrameTracker
    from core.sequence.tracks import subject_rows
    from core.synth import SynthConfig, synthesize
    from core.training import Trainer, frame_views

    synthesize(tmp / "capture", SynthConfig(frames=2, views=8, width=64, height=64, seed=3,
                                            priors=True, ao_directions=8))
    capture = load_capture(tmp / "capture")
    base = train_config("fast")
    cfg = replace(base, device=device, masks="subject", bake_ao=False, init_points=2000,
                  schedule=base.schedule.scaled(key_steps))
    selected = select_views(capture, masks=cfg.masks)
    key = Trainer(frame_views(capture, "000000", selected), cfg)
    key.train()
    key.step = cfg.schedule.stage3_start + 1  # profile stage-3 steps (every term)
    seq = SequenceConfig()
    views = frame_views(capture, "000001", selected)
    before = frame_views(capture, "000000", selected)
    model = key.model
    moving = subject_rows(model.means.detach(), [views, before], seq)
    ids = torch.arange(len(model))
    counter = SyncCounter()
    with counter:  # once a frame: the graph, the start race
        tracker = FrameTracker(views, model, ids, len(model), cfg, seq, moving=moving)
    setup = {"syncs": counter.syncs,
             "sync_lines": dict(counter.by_line.most_common(6))}
    return key, tracker, setup


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--key-steps", type=int, default=240,
                    help="steps the key frame trains before its steps are counted")
    ap.add_argument("--label", default="this tree")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    from core.device import resolve_device

    device = resolve_device(args.device)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        key, tracker, setup = build(Path(tmp), str(device), args.key_steps)
        rows["key frame (stage 3)"] = profile(key.train_step, args.steps, device)
        rows["tracked: deform"] = profile(tracker.train_step, args.steps, device)
        tracker.step = tracker.deform_steps  # the refine stage starts at the next step
        rows["tracked: refine"] = profile(tracker.train_step, args.steps, device)
    print(f"\nper step, {args.label}, {device.type}, {args.steps} steps each\n")
    print("| step | ops | launches | device syncs | host-only reads |")
    print("|---|---|---|---|---|")
    for name, r in rows.items():
        launches = "-" if r["launches"] is None else f"{r['launches']:.0f}"
        print(f"| {name} | {r['ops']:.0f} | {launches} | {r['syncs']:.1f} | "
              f"{r['host_only']:.1f} |")
    print(f"| tracked frame's setup (once a frame) | | | {setup['syncs']} | |")
    print(f"\ntracked frame's setup: syncs by where they come from")
    for line, n in setup["sync_lines"].items():
        print(f"  {n:6d}  {line}")
    for name, r in rows.items():
        print(f"\n{name}: syncs a step by where they come from")
        for line, n in r["sync_lines"].items():
            print(f"  {n:6.2f}  {line}")
    if args.json:
        args.json.write_text(json.dumps({"label": args.label, "device": device.type,
                                         "rows": rows, "setup": setup}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
