"""Relighting and meshes on a synthetic capture, each beside its baseline (issue 7).

One reconstruction of a `dgs synth` capture (one frame), then:
- relit held-out views under the capture's second light (gt/lights.json, gt/relight) against
  ground truth: the method (visibility times the map's SH9 irradiance, albedo divided by the
  capture light's SH9 irradiance), the baseline without the AO term (visibility 1 in the
  shading), and docs/design.md's uniform capture irradiance (pi) instead of the stage's SH9 light;
- meshes (TSDF of the geometry branch's depth, docs/design.md section 5) against the ground-truth
  mesh: Chamfer distance (percent of the reference's diagonal) and normal consistency, beside
  the baseline that fuses the appearance branch's depth, at 512 and 256 voxels per diagonal.

    python benchmarks/relight.py [--preset fast|demo] [--views 16] [--size 128] [--seed 0]
                                 [--out DIR] [--quick]

`--preset demo` is `make demo`'s budget (2500 steps); `--quick` the test preset on 8 views of
48x48 (a check that the script runs). With --out, a finished reconstruction there is reused.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def reconstruct_once(capture: Path, run: Path, preset: str) -> dict:
    """The run's metrics: a finished run is reused, an interrupted one resumed."""
    from core.demo import DEMO_OVERRIDES
    from core.pipeline import reconstruct

    if (run / "metrics.json").is_file() and not any((run / "checkpoints").glob("*.pt")):
        metrics = json.loads((run / "metrics.json").read_text())
        if metrics.get("frames"):
            return metrics
    if preset == "demo":
        return reconstruct(capture, run, preset="test", overrides=DEMO_OVERRIDES, resume=True,
                           progress=False)
    return reconstruct(capture, run, preset=preset, resume=True, progress=False)


def relit_rows(run: Path, capture: Path) -> list[dict]:
    """Scores of the relit held-out views: the method, no AO, uniform capture light."""
    import numpy as np

    from core.config import read_run
    from core.evaluation import evaluate_run
    from core.relight.metrics import relit_heldout

    ev = evaluate_run(run)["relight"]
    rows = [{"variant": "SH9 capture light + AO (the method)", **{k: ev[k] for k in (
        "psnr", "psnr_full", "ssim")}},
            {"variant": "without the AO term (baseline)", "psnr": ev["psnr_no_ao"],
             "psnr_full": ev["psnr_full_no_ao"], "ssim": ev["ssim_no_ao"]}]
    # docs/design.md's default: a uniform capture irradiance of pi.
    resolved = read_run(run, capture)
    cams = list(resolved.views.split.scored)
    scores = []
    for frame in resolved.frames:
        scores += relit_heldout(run, capture, frame, cams, resolved.views.downscale,
                                sheet_maps=(), capture_light=None)["scores"]
    rows.append({"variant": "uniform capture light pi + AO (docs/design.md default)",
                 **{k: float(np.mean([s[k] for s in scores])) for k in ("psnr", "psnr_full", "ssim")}})
    return rows


def mesh_rows(run: Path, capture: Path, resolutions: tuple[int, ...]) -> list[dict]:
    import trimesh

    from core.config import MeshConfig
    from core.mesh import mesh_distance, mesh_run

    rows = []
    for depth in ("geometry", "appearance"):
        for res in resolutions:
            out = run / f"meshes_{depth}_{res}"
            t0 = time.perf_counter()
            result = mesh_run(run, out, config=MeshConfig(resolution=res, depth=depth))
            seconds = time.perf_counter() - t0
            for frame, info in result["frames"].items():
                pred = trimesh.load(out / f"{frame}.ply", force="mesh")
                ref = trimesh.load(capture / "gt" / "meshes" / f"{frame}.ply", force="mesh")
                d = mesh_distance(pred, ref)
                rows.append({"depth": depth, "resolution": res, "frame": frame,
                             "chamfer_pct": 100 * d["chamfer_relative"],
                             "normal_consistency": d["normal_consistency"],
                             "faces": info["faces"], "watertight": info["watertight"],
                             "seconds": seconds})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--preset", default="demo", choices=("demo", "fast", "paper", "test"))
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--seed", type=int, default=0, help="dgs synth seed of the capture")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--quick", action="store_true", help="test preset, 8 views of 48x48")
    args = ap.parse_args()
    resolutions = (512, 256)
    if args.quick:
        args.preset, args.views, args.size, resolutions = "test", 8, 48, (128,)
    from core.synth import SynthConfig, synthesize

    root = args.out or Path(tempfile.mkdtemp(prefix="dgs-relight-"))
    capture, run = root / "capture", root / f"run-{args.preset}"
    if not (capture / "capture.json").exists():
        synthesize(capture, SynthConfig(frames=1, views=args.views, width=args.size,
                                        height=args.size, seed=args.seed, priors=True))
    print(f"capture: {args.views} views, {args.size}x{args.size}, seed {args.seed}, preset "
          f"{args.preset}, output in {root}", flush=True)
    t0 = time.perf_counter()
    metrics = reconstruct_once(capture, run, args.preset)
    frame = next(iter(metrics["frames"].values()))
    print(f"reconstruction: {frame['gaussians']} Gaussians, {frame['seconds']:.0f} s "
          f"(this call {time.perf_counter() - t0:.0f} s)\n", flush=True)

    relit = relit_rows(run, capture)
    print("| relit held-out views, second light | PSNR figure (dB) | PSNR image (dB) | SSIM |")
    print("|---|---|---|---|")
    for r in relit:
        print(f"| {r['variant']} | {r['psnr']:.2f} | {r['psnr_full']:.2f} | {r['ssim']:.4f} |")
    meshes = mesh_rows(run, capture, resolutions)
    print("\n| mesh (TSDF of the depth of) | voxels / diagonal | Chamfer (% of diagonal) | "
          "normal consistency | faces | watertight | seconds |")
    print("|---|---|---|---|---|---|---|")
    for r in meshes:
        print(f"| {r['depth']} branch | {r['resolution']} | {r['chamfer_pct']:.3f} | "
              f"{r['normal_consistency']:.4f} | {r['faces']} | {r['watertight']} | "
              f"{r['seconds']:.1f} |")
    (root / "relight.json").write_text(json.dumps({"relit": relit, "meshes": meshes}, indent=2))


if __name__ == "__main__":
    main()
