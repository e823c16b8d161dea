"""The sequence stream and SPZ against the frame PLYs on finished runs (docs/benchmarks.md,
"Delivery"): bytes per frame, the decoded frames rendered against the uncompressed ones on the
held-out views of every frame (PSNR of the whole image; angle between the normal maps on the
pixels the geometry covers), encode and decode seconds per frame.

    python benchmarks/stream.py RUN [RUN ...] [--out DIR] [--position-pixels 0.05] ...

Runs come from `benchmarks/sequence.py --quick` (its OUT/sequential). The renders use each run's
own settings (SH degree, beta, screen blur) at its resolution, like `dgs eval`. SPZ is scored
with the PLY's geometry branch (SPZ carries appearance only: one opacity, no normals), so its
row measures what its quantization does to the picture.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import fields
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _views(run: Path):
    from core.data import load_capture
    from core.relight.gbuffer import run_render

    settings = run_render(run)
    capture = load_capture(settings.capture)
    cams = [settings.views.served(c) for c in settings.views.cameras(capture, "scored")]
    return settings, [settings.camera(c) for c in cams]


def _render(splats, camera, settings):
    import torch

    from core.model import GaussianModel
    from core.render import render

    model = GaussianModel(splats.to_params())
    with torch.no_grad():
        r = render(model, camera, sh_degree=settings.sh_degree, beta=settings.beta,
                   geometry=True, background=torch.tensor(settings.background),
                   eps2d=settings.eps2d, antialiased=settings.antialiased)
    return r.rgb.clamp(0, 1).numpy(), r.normal.numpy(), r.alpha_g.numpy()[..., 0]


def compare(a, b) -> tuple[float, float, float]:
    """(PSNR dB, mean and 99th-percentile normal angle in degrees) of render b against a."""
    rgb_a, n_a, cov = a
    rgb_b, n_b, _ = b
    mse = float(np.mean((rgb_a - rgb_b) ** 2))
    psnr = 10 * np.log10(1.0 / max(mse, 1e-12))
    on = cov > 0.5
    if not on.any():
        return psnr, 0.0, 0.0
    ua = n_a[on] / np.linalg.norm(n_a[on], axis=1, keepdims=True).clip(1e-9)
    ub = n_b[on] / np.linalg.norm(n_b[on], axis=1, keepdims=True).clip(1e-9)
    ang = np.degrees(np.arccos(np.clip((ua * ub).sum(1), -1, 1)))
    return psnr, float(ang.mean()), float(np.percentile(ang, 99))


def score_run(run: Path, out: Path, config, subject: bool = False) -> dict:
    """Export `run` as SPZ and stream into `out` and score both against its PLYs (with
    `subject`, the subject's alone against the subject's PLYs)."""
    from core.export.run import export_run
    from core.export.splats import read_frame_ply
    from core.export.spz import read_spz
    from core.export.stream import read_stream

    record = export_run(run, out, formats=("spz", "stream"), config=config, subject=subject)
    plys = out / "ply" if subject else None
    settings, cams = _views(run)
    start = time.perf_counter()
    header, frames = read_stream(out / "stream.dgss")
    decoded = list(frames)
    decode_s = (time.perf_counter() - start) / len(decoded)
    rows = {"stream": [], "spz": []}
    for name, dec in zip(header["frames"], decoded):
        ply = read_frame_ply(plys / f"{name}.ply" if plys is not None else
                             run / "frames" / name / "gaussians.ply")
        spz = read_spz(out / "spz" / f"{name}.spz")
        spz.opacity_g, spz.normals, spz.visibility = ply.opacity_g, ply.normals, ply.visibility
        for cam in cams:
            ref = _render(ply, cam, settings)
            rows["stream"].append(compare(ref, _render(dec, cam, settings)))
            rows["spz"].append(compare(ref, _render(spz, cam, settings)))
    result = {"frames": len(decoded), "views": len(cams), "ply_bytes": record["ply_bytes_per_frame"],
              "decode_s": decode_s, "gaussians": float(np.mean([len(d) for d in decoded]))}
    for fmt in ("stream", "spz"):
        v = np.array(rows[fmt])
        result[fmt] = {"bytes": record[fmt]["bytes_per_frame"],
                       "ratio": record[fmt]["ratio_to_ply"],
                       "encode_s": record[fmt]["encode_seconds_per_frame"],
                       "psnr_min": float(v[:, 0].min()), "psnr_mean": float(v[:, 0].mean()),
                       "normal_mean_deg": float(v[:, 1].mean()),
                       "normal_p99_deg": float(v[:, 2].max())}
    return result


def main(argv: list[str] | None = None) -> int:
    from core.export.codec import StreamConfig

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", help="finished run directories")
    ap.add_argument("--out", default="/tmp/dgs-bench-stream")
    for f in fields(StreamConfig):
        ap.add_argument(f"--{f.name.replace('_', '-')}", type=type(f.default), default=f.default)
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(max(1, torch.get_num_threads()))
    config = StreamConfig(**{f.name: getattr(args, f.name) for f in fields(StreamConfig)})
    results = {}
    for i, run in enumerate(args.runs):
        results[run] = score_run(Path(run), Path(args.out) / str(i), config)
        print(run, json.dumps(results[run]), flush=True)
    print("| run | format | kB / frame | x smaller than PLY | PSNR min / mean (dB) | normals mean / "
          "worst p99 (deg) | encode / decode (ms / frame) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for run, r in results.items():
        print(f"| {Path(run).parent.name} | PLY | {r['ply_bytes'] / 1e3:.1f} | 1 | - | - | - |")
        for fmt in ("spz", "stream"):
            s = r[fmt]
            dec = f"{r['decode_s'] * 1e3:.0f}" if fmt == "stream" else "-"
            print(f"| {Path(run).parent.name} | {fmt} | {s['bytes'] / 1e3:.1f} | {s['ratio']:.1f} | "
                  f"{s['psnr_min']:.2f} / {s['psnr_mean']:.2f} | {s['normal_mean_deg']:.2f} / "
                  f"{s['normal_p99_deg']:.2f} | {s['encode_s'] * 1e3:.0f} / {dec} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
