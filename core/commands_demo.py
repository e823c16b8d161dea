"""`dgs demo`: the main job on a small built-in capture (what `make demo` runs).

synth (once) -> reconstruct -> evaluate -> a contact sheet of the held-out views. With the
service extra installed, the service package takes this command over (`service.demo`: the same
job through an embedded `dgs serve`, registered through the dgs.commands entry point so core
never imports the service); here it runs in this process. `--raster` runs the earlier
rasterizer-only demo (`core.demo_raster`) instead.
"""

from __future__ import annotations

import argparse
import shutil
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

__all__ = ["DEMO_OVERRIDES", "DEMO_SYNTH", "contact_sheet", "demo_capture", "register",
           "report", "run_demo"]

# Between the `test` (500) and `fast` (7.5k) presets: 2500 steps take about two minutes on two
# CPU cores for 14 training views of 128x128, long enough for the geometry branch to settle
# (the paper preset's stage proportions).
DEMO_OVERRIDES = {"train": {"schedule": {
    "iterations": 2500, "stage2_start": 625, "stage3_start": 1875, "sh_interval": 75,
    "densify_from": 40, "densify_until": 1500, "densify_interval": 40, "reset_interval": 625},
    "init_points": 5000, "rates": {"means_decay_steps": 2500},
    "densify": {"max_gaussians": 20000}}}
# The built-in capture (core.synth.SynthConfig fields).
DEMO_SYNTH = {"frames": 1, "views": 16, "width": 128, "height": 128, "seed": 0, "priors": True}
COLUMNS = ("capture", "render", "normal", "AO", "ground-truth normal")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the main job on a small built-in capture")
    p.add_argument("--out", default="demo", help="demo folder (default ./demo)")
    p.add_argument("--raster", action="store_true",
                   help="only the rasterizer demo (ground-truth splats, no training)")
    p.add_argument("--in-process", action="store_true",
                   help="run the job in this process, not through the HTTP service")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    if args.raster:
        from core.demo_raster import run_raster_demo

        return run_raster_demo(args.out)
    if not args.in_process:
        print("dgs demo: the service extra is not installed, so the job runs in this process "
              "(pip install -e '.[service]' to run it through the HTTP service)", flush=True)
    return run_demo(args.out)


def _tile(path: Path, size: tuple[int, int]) -> np.ndarray:
    from PIL import Image

    if not path.is_file():
        return np.zeros((size[1], size[0], 3), np.uint8)
    img = Image.open(path).convert("RGB").resize(size, Image.NEAREST)
    return np.asarray(img)


def _capture_tile(capture_dir: Path, frame: str, cam: str, size: tuple[int, int]) -> np.ndarray:
    """The captured view as the camera saw it: straight colour times its coverage mask (on the
    black of the synthetic studio)."""
    from PIL import Image

    image = _tile(capture_dir / "images" / frame / f"{cam}.png", size).astype(np.float32)
    mask = capture_dir / "masks" / frame / f"{cam}.png"
    if mask.is_file():
        cover = np.asarray(Image.open(mask).convert("L").resize(size, Image.NEAREST)) / 255.0
        image = image * cover[..., None]
    return (image + 0.5).astype(np.uint8)


def contact_sheet(capture_dir: Path, run_dir: Path, frame: str, cameras: list[str],
                  out: Path, scale: int = 2) -> Path:
    """One row per held-out camera: capture | render | normal | AO | ground-truth normal,
    upscaled by `scale` (nearest) with a label row on top."""
    from PIL import Image, ImageDraw

    rows = []
    for cam in cameras:
        first = Image.open(capture_dir / "images" / frame / f"{cam}.png")
        size = (first.width * scale, first.height * scale)
        r = run_dir / "renders" / frame
        gt = capture_dir / "gt" / "normals" / frame / f"{cam}.npy"
        tiles = [_capture_tile(capture_dir, frame, cam, size),
                 _tile(r / f"{cam}_rgb.png", size), _tile(r / f"{cam}_normal.png", size),
                 _tile(r / f"{cam}_ao.png", size)]
        if gt.is_file():
            n = np.load(gt)
            fg = np.linalg.norm(n, axis=-1, keepdims=True) > 0.5
            img = ((np.where(fg, (n + 1) / 2, 0)) * 255 + 0.5).astype(np.uint8)
            tiles.append(np.asarray(Image.fromarray(img).resize(size, Image.NEAREST)))
        else:
            tiles.append(np.zeros_like(tiles[0]))
        rows.append(np.concatenate(tiles, axis=1))
    body = np.concatenate(rows, axis=0)
    label_h = 16
    sheet = Image.new("RGB", (body.shape[1], body.shape[0] + label_h), (255, 255, 255))
    sheet.paste(Image.fromarray(body), (0, label_h))
    draw = ImageDraw.Draw(sheet)
    width = body.shape[1] // len(COLUMNS)
    for i, name in enumerate(COLUMNS):
        draw.text((i * width + 4, 2), name, fill=(0, 0, 0))
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)
    return out


def _synth_config(capture_dir: Path) -> dict | None:
    """The `dgs synth` configuration recorded in a capture (None if another source)."""
    import json

    record = json.loads((capture_dir / "capture.json").read_text()).get("synth") or {}
    return record.get("config")


def demo_capture(capture_dir: Path, synth: dict | None = None, step: str = "[1/4]"):
    """The demo's synthetic capture in `capture_dir` (`synth`: SynthConfig fields, default
    DEMO_SYNTH), made unless an earlier demo made the same one; returns it checked."""
    from core.data import check_capture
    from core.synth import SynthConfig, synthesize

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
    """The contact sheet of the held-out views and the printed results; returns the sheet."""
    frame = capture.frames[0]
    held = [c.id for i, c in enumerate(capture.cameras) if i % 8 == 0]
    sheet = contact_sheet(capture_dir, run_dir, frame, held, run_dir / "contact_sheet.png")
    m = metrics["frames"][frame]
    print(f"{step} results", flush=True)
    print(f"      reconstruction: {train_s:.0f} s, {m['gaussians']} Gaussians, training PSNR "
          f"{m['train_psnr']:.2f} dB")
    print(f"      held-out views ({', '.join(held)}): PSNR {result['psnr']:.2f} dB on the "
          f"figure ({result['psnr_full']:.2f} dB whole image), SSIM "
          f"{result['ssim']:.3f}, normal cosine {result['normal_cos']:.3f} "
          f"({result['normal_deg']:.1f} deg mean error vs ground truth)")
    print(f"      pictures: {run_dir / 'renders' / frame}, plots: {run_dir / 'plots'}")
    print(f"      contact sheet: {sheet} ({' | '.join(COLUMNS)})")
    return sheet


def run_demo(out: str = "demo") -> int:
    from core.evaluate import evaluate_run
    from core.pipeline import reconstruct

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
