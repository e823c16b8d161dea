"""Rasterizer benchmark: time and peak memory of the native CPU rasterizer.

For (10k, 100k, 300k Gaussians) x (256^2, 512^2), C=3, G=5, it measures forward and
forward+backward of the disentangled pass (both branches), the same native code as a plain
single-opacity RGB pass (appearance branch only), and the dense PyTorch reference where it fits
in memory (small scenes only: it needs O(N * H * W) memory). It also breaks the 100k / 512^2
case into its stages, and with --check compares native and reference on freshly drawn scenes.

Each measurement runs in its own process; peak memory is the high-water mark of resident memory
during one forward+backward (after a warm-up) above the resident memory before it. Prints
Markdown tables.

    python benchmarks/rasterizer.py [--scene surface|volume|both] [--quick] [--check]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

GRID = [(10_000, 256), (10_000, 512), (100_000, 256), (100_000, 512), (300_000, 256),
        (300_000, 512)]
REFERENCE_GRID = [(1_000, 128), (3_000, 128)]
QUICK_GRID = [(10_000, 256), (100_000, 512)]


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _reset_peak() -> None:
    """Reset the process's peak RSS (VmHWM) so the next reading is the peak of what follows."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def _peak_mb() -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _child(spec: dict) -> dict:
    """Runs in a fresh process: build the scene, warm up, measure."""
    import torch

    from bench_scenes import surface_scene, volume_scene
    from native import rasterize

    make = surface_scene if spec["scene"] == "surface" else volume_scene
    s = make(spec["n"], spec["res"], spec["res"], C=3, G=5, seed=spec.get("seed", 0))
    mode = spec["mode"]
    backend = "reference" if mode == "reference" else "native"
    geometry = None if mode == "rgb" else s.geometry
    opacity_g = s.opacity_c if mode == "rgb" else s.opacity_g
    beta = 0.0 if mode == "rgb" else 0.3
    leaves = [s.means, s.quats, s.scales, s.opacity_c, s.colors] + (
        [] if mode == "rgb" else [s.opacity_g, s.geometry])
    for t in leaves:
        t.requires_grad_(True)

    def run(backward: bool) -> None:
        out = rasterize(s.means, s.quats, s.scales, s.opacity_c, opacity_g, s.colors, geometry,
                        s.viewmat, s.K, s.width, s.height, beta=beta, eps2d=0.1,
                        antialiased=True, backend=backend)
        if backward:
            loss = out.color.sum()
            if geometry is not None:
                loss = loss + out.geometry.sum() + out.depth.sum() + out.alpha_g.sum()
            loss.backward()
            for t in leaves:
                t.grad = None

    if backend == "native":
        import native._backend

        native._backend.load()
    run(True)  # warm-up (first-call allocations, thread pool)
    base = _rss_mb()
    _reset_peak()
    run(True)  # the peak-memory sample
    peak = _peak_mb() - base
    reps = spec.get("reps", 5)
    fwd, full = [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        with torch.no_grad():
            run(False)
        fwd.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        run(True)
        full.append(time.perf_counter() - t0)
    return {"fwd_ms": 1e3 * sorted(fwd)[reps // 2], "full_ms": 1e3 * sorted(full)[reps // 2],
            "peak_mb": peak, "threads": torch.get_num_threads()}


def measure(spec: dict) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)],
                         capture_output=True, text=True, timeout=1800)
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr else "failed"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _stages(scene_kind: str) -> dict[str, float]:
    """Time of each native stage at 100k Gaussians, 512^2 (median of 5)."""
    import torch

    from bench_scenes import surface_scene, volume_scene
    from native._backend import load

    ext = load()
    s = (surface_scene if scene_kind == "surface" else volume_scene)(100_000, 512, 512)
    W = H = 512
    args = (s.means, s.quats, s.scales, s.opacity_c, s.opacity_g, s.viewmat, s.K, W, H, 0.3, 0.1,
            True, 0.01, 1e10)

    def timed(fn):
        ts, r = [], None
        for _ in range(5):
            t0 = time.perf_counter()
            r = fn()
            ts.append(time.perf_counter() - t0)
        return r, 1e3 * sorted(ts)[2]

    (m2, cn, dp, op, rects, _), t_proj = timed(lambda: ext.projection_fwd(*args))
    (off, ids), t_bin = timed(lambda: ext.intersect_tiles(rects, dp, W, H, 16))
    (col, geo, dep, tr, st, _), t_fwd = timed(lambda: ext.rasterize_fwd(
        m2, cn, op, dp, s.colors, s.geometry, rects, off, ids, W, H, 16, True))
    g = [torch.randn_like(col), torch.randn_like(geo), torch.randn_like(dep), torch.randn(H, W, 2)]
    _, t_bwd = timed(lambda: ext.rasterize_bwd(m2, cn, op, dp, s.colors, s.geometry, rects, off,
                                               ids, W, H, 16, True, col, geo, dep, tr, st, *g))
    _, t_pbwd = timed(lambda: ext.projection_bwd(*args[:-2], 0.01, 1e10, m2, cn, dp, op))
    return {"projection": t_proj, "binning + sort": t_bin, "blend forward": t_fwd,
            "blend backward": t_bwd, "projection backward": t_pbwd,
            "pairs (Gaussian, tile)": float(ids.numel())}


def _check(n_scenes: int) -> list[str]:
    """Native vs reference on scenes drawn now (seeds no test uses)."""
    sys.path.insert(0, str(HERE.parent / "tests" / "native"))
    from compare import compare
    from scenes import random_scene

    lines = ["| seed | N | size | beta | antialiased | ambiguous px | max fwd rel err "
             "| max grad rel err |", "|---|---|---|---|---|---|---|---|"]
    base = int(time.time()) % 100_000 + 1_000
    for i in range(n_scenes):
        seed = base + i
        n, beta, aa = (500, 1500)[i % 2], (0.0, 0.3, 0.7, 1.0)[i % 4], bool(i % 2)
        scene = random_scene(n, 96, 72, seed=seed, behind=0.05, offscreen=0.05)
        r = compare(scene, seed=seed, beta=beta, antialiased=aa)
        f, g = r.worst()
        lines.append(f"| {seed} | {n} | 96x72 | {beta} | {aa} | {r.ambiguous} | {f:.2e} | {g:.2e} |")
    return lines


def _fmt(r: dict, key: str) -> str:
    return "n/a" if "error" in r else f"{r[key]:.1f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scene", choices=["surface", "volume", "both"], default="both")
    ap.add_argument("--quick", action="store_true", help="two sizes only")
    ap.add_argument("--check", action="store_true", help="also compare with the reference")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(_child(json.loads(args.child))))
        return
    import torch

    print(f"threads: {torch.get_num_threads()}, torch {torch.__version__}, "
          f"cpu: {os.cpu_count()} cores")
    kinds = ["surface", "volume"] if args.scene == "both" else [args.scene]
    for kind in kinds:
        print(f"\n### {kind} scene, C=3, G=5 (milliseconds, MB)\n")
        print("| N | size | both fwd | both fwd+bwd | both peak MB | RGB-only fwd | RGB-only "
              "fwd+bwd | RGB-only peak MB | both / RGB-only (fwd+bwd) |")
        print("|---|---|---|---|---|---|---|---|---|")
        for n, res in (QUICK_GRID if args.quick else GRID):
            both = measure({"scene": kind, "n": n, "res": res, "mode": "both"})
            rgb = measure({"scene": kind, "n": n, "res": res, "mode": "rgb"})
            ratio = ("n/a" if "error" in both or "error" in rgb
                     else f"{both['full_ms'] / rgb['full_ms']:.2f}x")
            print(f"| {n:,} | {res}^2 | {_fmt(both, 'fwd_ms')} | {_fmt(both, 'full_ms')} | "
                  f"{_fmt(both, 'peak_mb')} | {_fmt(rgb, 'fwd_ms')} | {_fmt(rgb, 'full_ms')} | "
                  f"{_fmt(rgb, 'peak_mb')} | {ratio} |", flush=True)
        print(f"\n#### {kind}: native vs dense reference (where the reference fits)\n")
        print("| N | size | native fwd+bwd | native peak MB | reference fwd+bwd | reference peak MB "
              "| speed-up |")
        print("|---|---|---|---|---|---|---|")
        for n, res in REFERENCE_GRID:
            nat = measure({"scene": kind, "n": n, "res": res, "mode": "both"})
            ref = measure({"scene": kind, "n": n, "res": res, "mode": "reference", "reps": 2})
            speed = ("n/a" if "error" in nat or "error" in ref
                     else f"{ref['full_ms'] / nat['full_ms']:.0f}x")
            print(f"| {n:,} | {res}^2 | {_fmt(nat, 'full_ms')} | {_fmt(nat, 'peak_mb')} | "
                  f"{_fmt(ref, 'full_ms')} | {_fmt(ref, 'peak_mb')} | {speed} |", flush=True)
        print(f"\n#### {kind}: where the time goes, 100k Gaussians, 512^2 (ms)\n")
        st = _stages(kind)
        print("| stage | ms |\n|---|---|")
        for k, v in st.items():
            print(f"| {k} | {v:,.1f} |" if "pairs" not in k else f"| {k} | {v:,.0f} |")
        total = sum(v for k, v in st.items() if "pairs" not in k)
        print(f"| total | {total:.1f} |", flush=True)
    if args.check:
        print("\n### native vs reference on scenes no test has seen\n")
        print("\n".join(_check(8)))


if __name__ == "__main__":
    main()
