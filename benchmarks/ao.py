"""Where the AO bake's time goes, on a trained model of a real capture (issue 23).

The bake of a key frame (`core.ao.GaussianAOBaker`): per-Gaussian rays (64 about each normal) and
per-pixel maps of every training view (renders at 1/4 of the training resolution, 64 rays per
covered pixel, joint-bilateral filter). Timed in parts, then the tracer alone under variations
that say what it spends on: the number of rays, the tree, the transparent Gaussians.

    python benchmarks/ao.py MODEL CAPTURE [--downscale 4] [--threads 2] [--quick]

MODEL is a checkpoint (RUN/checkpoints/<frame>.pt) or a Gaussian PLY (RUN/frames/<f>/
gaussians.ply); CAPTURE the capture it was trained on. Before stage 2 a model's normals are its
initial +z and its geometry opacity its appearance one (what the bake would see then).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def load_model(path: Path):
    from core.model import GaussianModel

    if path.suffix == ".ply":
        return GaussianModel.load_ply(path)
    blob = torch.load(path, map_location="cpu", weights_only=True)
    return GaussianModel(blob["params"])


def training_views(capture_dir: Path, downscale: float):
    from core.data import load_capture
    from core.data.dataset import CaptureDataset
    from core.render import RenderCamera
    from core.training import training_cameras

    cap = load_capture(capture_dir)
    ds = CaptureDataset(cap, frames=cap.frames[:1],
                        cameras=[c.id for c in training_cameras(cap)], downscale=downscale)
    return [RenderCamera.from_camera(ds.served_camera(c)) for c in ds.cameras]


def timed(fn, *args, **kwargs):
    """The result and the seconds of CPU time this process spent on it: with one thread the
    work itself, whatever else shares the machine (wall time on a shared machine is not)."""
    start = time.process_time()
    out = fn(*args, **kwargs)
    return out, time.process_time() - start


def bake_parts(model, cameras, beta: float) -> list[tuple[str, float, str]]:
    """The bake in its parts: renders for the maps, one trace of every ray, the filters."""
    from core.ao import _map, _origins, _trace
    from core.config import AOConfig
    from native import gaussian_rays

    cfg = AOConfig()
    with torch.no_grad():
        views, t_render = timed(lambda: [_origins(model, c, beta, cfg) for c in cameras])
        offset, exclude = gaussian_rays(model.means, model.scales)
        _, t_own = timed(_trace, model, model.means.detach(), model.normals.detach(), offset,
                         exclude, cfg)
        pts = torch.cat([o.points for o in views])
        vis, t_maps = timed(_trace, model, pts, torch.cat([o.normals for o in views]),
                            torch.cat([o.offset for o in views]), None, cfg)
        parts = vis.split([o.points.shape[0] for o in views])
        _, t_filter = timed(lambda: [_map(o, v, c, cfg) for o, v, c in zip(views, parts,
                                                                           cameras)])
    n, m = len(model), pts.shape[0]
    return [("renders of the views at 1/4 (depth, normals)", t_render, f"{len(cameras)} views"),
            ("per-Gaussian rays", t_own, f"{n} x {cfg.n_dirs} = {n * cfg.n_dirs / 1e6:.1f}M rays"),
            ("per-pixel rays", t_maps, f"{m} x {cfg.n_dirs} = {m * cfg.n_dirs / 1e6:.1f}M rays"),
            ("upsample + joint bilateral filter", t_filter, "")]


def tracer_variants(model, sample: int = 20_000) -> list[tuple[str, float, str]]:
    """The tracer on a random sample of the Gaussians' own rays, under variations."""
    from native import gaussian_rays, trace_visibility

    g = torch.Generator().manual_seed(0)
    idx = torch.randperm(len(model), generator=g)[:sample]
    means, quats, scales = (model.means.detach(), model.quats.detach(), model.scales.detach())
    op, normals = model.opacity_g.detach(), model.normals.detach()
    offset, exclude = gaussian_rays(means, scales)

    def run(n_dirs=64, opacity=op, keep=None):
        m, q, s, o = means, quats, scales, opacity
        ex = exclude[idx]
        if keep is not None:
            m, q, s, o = m[keep], q[keep], s[keep], o[keep]
            ex = torch.full_like(ex, -1)  # indices change; the own Gaussian stays out by offset
        return trace_visibility(means[idx], normals[idx], m.contiguous(), q.contiguous(),
                                s.contiguous(), o.contiguous(), n_dirs=n_dirs,
                                offset=offset[idx], exclude=ex)

    base, t = timed(run)
    rows = [("64 rays, every Gaussian", t, f"mean visibility {float(base.mean()):.3f}")]
    _, t16 = timed(run, n_dirs=16)
    rows.append(("16 rays", t16, f"{t16 / t:.2f}x the time of 64"))
    for cut in (0.05, 0.2):
        keep = op >= cut
        vis, tk = timed(run, keep=keep)
        rows.append((f"only opacity_g >= {cut} ({int(keep.sum())} of {len(model)})", tk,
                     f"visibility +{float((vis - base).mean()):.3f}"))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("model", type=Path)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--beta", type=float, default=0.46, help="beta at the bake (fast: 0.46)")
    ap.add_argument("--quick", action="store_true", help="a tenth of the views")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    model = load_model(args.model)
    cameras = training_views(args.capture, args.downscale)
    if args.quick:
        cameras = cameras[::10]
    print(f"{len(model)} Gaussians, {len(cameras)} views of {cameras[0].width}x"
          f"{cameras[0].height}, {args.threads} threads; CPU seconds\n")
    print("| part | CPU s | what |\n|---|---|---|")
    total = 0.0
    for name, secs, what in bake_parts(model, cameras, args.beta):
        total += secs
        print(f"| {name} | {secs:.1f} | {what} |", flush=True)
    print(f"| **bake** | **{total:.1f}** | |\n")
    print("| tracer, 20k Gaussians' rays | CPU s | |\n|---|---|---|")
    for name, secs, what in tracer_variants(model):
        print(f"| {name} | {secs:.2f} | {what} |", flush=True)


if __name__ == "__main__":
    main()
