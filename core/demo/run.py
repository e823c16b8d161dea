"""The main job on a small built-in capture, in this process (`dgs demo --in-process`; what
`make demo` runs through the service, `service.demo`): synth (once) -> reconstruct (meshes
included) -> evaluate (held-out views, relit views, meshes, the contact sheet)."""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict
from pathlib import Path

from core.data import check_capture
from core.evaluation import evaluate_run
from core.pipeline import reconstruct
from core.synth import SynthConfig, synthesize

__all__ = ["DEMO_OVERRIDES", "DEMO_SYNTH", "demo_capture", "report", "run_demo"]

# Between the `test` (500) and `fast` (7.5k) presets: 2500 steps take about two minutes on two
# CPU cores for 14 training views of 128x128, long enough for the geometry branch to settle
# (the paper preset's stage proportions). The mesh at the design's 512 voxels per diagonal (the
# test preset's own 128 are for tiny test captures).
DEMO_OVERRIDES = {"train": {"schedule": {
    "iterations": 2500, "stage2_start": 625, "stage3_start": 1875, "sh_interval": 75,
    "densify_from": 40, "densify_until": 1500, "densify_interval": 40, "reset_interval": 625},
    "init_points": 5000, "rates": {"means_decay_steps": 2500},
    "densify": {"max_gaussians": 20000}}, "mesh": {"resolution": 512}}
# The built-in capture (core.synth.SynthConfig fields).
DEMO_SYNTH = {"frames": 1, "views": 16, "width": 128, "height": 128, "seed": 0, "priors": True}


def _synth_config(capture_dir: Path) -> dict | None:
    """The `dgs synth` configuration recorded in a capture (None if another source)."""
    record = json.loads((capture_dir / "capture.json").read_text()).get("synth") or {}
    return record.get("config")


def demo_capture(capture_dir: Path, synth: dict | None = None, step: str = "[1/4]"):
    """The demo's synthetic capture in `capture_dir` (`synth`: SynthConfig fields, default
    DEMO_SYNTH), made unless an earlier demo made the same one; returns it checked."""
    t0 = time.perf_counter()
    config = SynthConfig(**(synth or DEMO_SYNTH))
    if (capture_dir / "capture.json").exists() and _synth_config(capture_dir) != asdict(config):
        shutil.rmtree(capture_dir)  # made by an earlier `dgs synth` (other images): make it again
    if not (capture_dir / "capture.json").exists():
        print(f"{step} dgs synth -> {capture_dir} ({config.views} views, {config.width}x"
              f"{config.height}, {config.frames} frame(s)"
              f"{', normal priors' if config.priors else ''})", flush=True)
        synthesize(capture_dir, config)
    capture = check_capture(capture_dir)
    print(f"{step} capture: {len(capture.cameras)} cameras x {len(capture.frames)} frame(s) "
          f"({time.perf_counter() - t0:.0f} s)", flush=True)
    return capture


def report(capture, capture_dir: Path, run_dir: Path, metrics: dict, result: dict,
           train_s: float, step: str = "[4/4]") -> Path:
    """Print the results of the evaluated run; returns its contact sheet (written by
    `evaluate_run`)."""
    frame = capture.frames[0]
    held = result["split"]["heldout"]
    m = metrics["frames"][frame]
    print(f"{step} results", flush=True)
    print(f"      reconstruction: {train_s:.0f} s, {m['gaussians']} Gaussians, training PSNR "
          f"{m['train_psnr']:.2f} dB")
    print(f"      held-out views ({', '.join(held)}): PSNR {result['psnr']:.2f} dB on the "
          f"figure ({result['psnr_full']:.2f} dB whole image), SSIM "
          f"{result['ssim']:.3f}, normal cosine {result['normal_cos']:.3f} "
          f"({result['normal_deg']:.1f} deg mean error vs ground truth)")
    relit = result.get("relight")
    if relit:
        print(f"      relit under the second light: PSNR {relit['psnr']:.2f} dB on the figure "
              f"({relit['psnr_full']:.2f} dB whole image), SSIM {relit['ssim']:.3f}; without "
              f"the AO term {relit['psnr_no_ao']:.2f} dB")
    mesh = result.get("mesh")
    if mesh:
        print(f"      mesh: Chamfer {100 * mesh['chamfer_relative']:.2f}% of the diagonal, "
              f"normal consistency {mesh['normal_consistency']:.3f} ({run_dir / 'meshes'})")
    sheet = run_dir / result["contact_sheet"]
    print(f"      pictures: {run_dir / 'renders' / frame}, plots: {run_dir / 'plots'}")
    print(f"      contact sheet: {sheet} (capture, render, normal, AO, relit)")
    return sheet


def run_demo(out: str = "demo") -> int:
    root = Path(out)
    capture_dir, run_dir = root / "capture", root / "run"
    t0 = time.perf_counter()
    capture = demo_capture(capture_dir)
    if (run_dir / "config.json").is_file():
        shutil.rmtree(run_dir)  # a finished demo run: the demo shows the job, so run it again
    iterations = DEMO_OVERRIDES["train"]["schedule"]["iterations"]
    print(f"[2/4] dgs reconstruct {capture_dir} --out {run_dir} (test preset stretched to "
          f"{iterations} iterations; the native rasterizer builds on first use)", flush=True)
    t1 = time.perf_counter()
    metrics = reconstruct(capture_dir, run_dir, preset="test", overrides=DEMO_OVERRIDES)
    train_s = time.perf_counter() - t1
    print("[3/4] dgs eval", run_dir, flush=True)
    result = evaluate_run(run_dir)
    report(capture, capture_dir, run_dir, metrics, result, train_s)
    print(f"      total {time.perf_counter() - t0:.0f} s")
    return 0
