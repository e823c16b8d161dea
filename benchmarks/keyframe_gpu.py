"""GPU: one whole key frame, ours against a plain 3DGS trainer on gsplat, in one run (issue 24).

Both train on the same capture, frame, training views (every camera but each 8th), resolution,
initial Gaussians (our seeding: the capture's points, else triangulated, else random), and the
same number of steps with the same step-to-view order rule (each view once per epoch):

- ours: `core.training.Trainer` at the `paper` preset scaled to `--steps` (the three stages,
  the geometry branch with its normal and depth-normal losses, the AO bake at stage 3's first
  step, SH degree 3), on CUDA;
- gsplat: a plain 3DGS trainer on gsplat's library API, as gsplat's examples/simple_trainer.py
  trains (`gsplat.rasterization`, classic mode, `DefaultStrategy` with its step counts scaled
  by the same factor, Adam per parameter with 3DGS's rates, the position rate decaying to
  1/100 over the run, SH degree raised every 1000 steps scaled), with our photometric loss
  (0.8 L1 + 0.2 D-SSIM, as 3DGS) so the losses are the same; the installed `DefaultStrategy`
  as it is: released gsplat 1.5.3 never resets opacities (its reset condition
  `step % reset_every == 0 & step > 0` never holds; gsplat pull request 776 fixed it after);
- gsplat-3dgs: the same with 3DGS's opacity resets, made by this script (gsplat's own
  `reset_opa`, to 0.01 at each reset step inside the refine window) when the installed
  strategy skips them;
- ours-3dgs: our trainer's plain 3DGS (`train.method` 3dgs on the same schedule), beside them.

Reported per system: seconds per stage and steps/s (the device synchronized at each stage
boundary), the AO bake's seconds, the whole frame's seconds, peak GPU memory
(`torch.cuda.max_memory_allocated` over the training), Gaussians at the end, held-out PSNR
(whole image) and SSIM with `dgs eval`'s view scores on 8-bit renders (what `dgs eval`
scores), normal agreement where the capture has ground-truth normals; then, for each, the
host synchronisations per step (torch profiler over `--profile-steps` further steps: calls
of cudaStreamSynchronize / cudaDeviceSynchronize / device-to-host copies) and the top CUDA
kernels; then a mesh of our frame at `--mesh-voxels` (`core.mesh.build.mesh_model`).

    python benchmarks/keyframe_gpu.py CAPTURE --out DIR [--steps 3000] [--downscale 1]
                                      [--systems ours gsplat ...] [--frame ID]

CAPTURE is a canonical capture or anything `dgs import` reads (the instant-ngp fox folder);
DIR receives result.json after every part (a run cut short keeps what it measured) and the
profiles. gsplat: see benchmarks/gpu.py for its wheel and JIT build (start the build early in
another process: `python -c "from gsplat.cuda._backend import _C"`; torch's build lock makes
this script wait for it).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import traceback
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from core.color import linear_to_srgb  # noqa: E402
from core.config import method_defaults, select_views, train_config  # noqa: E402
from core.data import CaptureDataset, import_capture, load_capture  # noqa: E402
from core.evaluation.run import _view_metrics  # noqa: E402
from core.losses import depth_to_normals, photometric_loss  # noqa: E402
from core.model import GaussianModel  # noqa: E402
from core.pipeline.outputs import COVERAGE, _to8  # noqa: E402
from core.render import RenderCamera, render  # noqa: E402
from core.seeding import scene_extent, seed_points  # noqa: E402
from core.training import Trainer  # noqa: E402
from core.training.callbacks import Callback  # noqa: E402
from core.training.views import frame_views  # noqa: E402

SYNC_OPS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize",
            "aten::_local_scalar_dense", "aten::item", "aten::nonzero")


SYSTEMS = ("ours", "ours-3dgs", "gsplat", "gsplat-3dgs")
"""What `--systems` picks from (module docstring)."""


def sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def reset_peak() -> None:
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()


def peak_gb() -> float:
    return round(torch.cuda.max_memory_allocated() / 2**30, 3) if torch.cuda.is_available() \
        else 0.0


class StageClock(Callback):
    """Seconds and steps of each stage: the device is synchronized after a stage's last step
    only (`ends`: the steps that start a new stage, and the last)."""

    def __init__(self, ends: set[int] = frozenset()):
        self.seconds: dict[str, float] = {}
        self.steps: dict[str, int] = {}
        self.ends = set(ends)
        self.t = 0.0

    def start(self) -> None:
        sync()
        self.t = time.perf_counter()

    def count(self, stage: str, step: int, last: bool) -> None:
        self.steps[stage] = self.steps.get(stage, 0) + 1
        if last or step + 1 in self.ends:
            sync()
            now = time.perf_counter()
            self.seconds[stage] = self.seconds.get(stage, 0.0) + now - self.t
            self.t = now

    def on_train_start(self, trainer) -> None:
        self.start()

    def on_step_end(self, trainer, info) -> None:
        self.count(f"stage {info.plan.stage}", info.step, info.step == trainer.iterations - 1)

    def table(self) -> dict:
        return {k: {"seconds": round(s, 3), "steps": self.steps[k],
                    "steps_per_s": round(self.steps[k] / max(s, 1e-9), 2)}
                for k, s in self.seconds.items()}


def held_out(capture, frame: str, downscale: float, draw, background: np.ndarray) -> dict:
    """Mean scores of `draw(camera) -> ((H, W, 3) rgb, (H, W, 3) unit normals, (H, W) covered)`
    over the held-out cameras, as `dgs eval` scores them (`core.evaluation.run._view_metrics`
    on the pictures a run writes: 8-bit colour, the normal picture black where not covered,
    against the capture's ground-truth normals or its priors)."""
    held = [c.id for i, c in enumerate(capture.cameras) if i % 8 == 0]
    ds = CaptureDataset(capture, frames=[frame], cameras=held, downscale=downscale)
    rows = []
    for i in range(len(ds)):
        s = ds[i]
        with torch.no_grad():
            rgb, normal, covered = draw(s.camera)
        image = capture.image_path(frame, s.camera_id)
        linear = image is not None and image.suffix.lower() == ".exr"
        rgb = rgb.float().clamp(0, 1).cpu().numpy()
        rgb8 = _to8(linear_to_srgb(rgb) if linear else rgb) / 255.0  # as the run's PNG
        png = _to8(np.where(covered.cpu().numpy()[..., None],
                            (normal.float().cpu().numpy() + 1) / 2, 0.0)) / 255.0
        gt = capture.root / "gt" / "normals" / frame / f"{s.camera_id}.npy"
        rows.append(_view_metrics(s, rgb8.astype(np.float32), png.astype(np.float32),
                                  np.load(gt) if gt.is_file() else None, background, linear))
    keys = ("psnr", "psnr_full", "ssim", "normal_cos", "normal_deg")
    return {k: float(np.mean([r[k] for r in rows if r.get(k) is not None]))
            for k in keys if any(r.get(k) is not None for r in rows)}


def host_syncs(step, n: int, out: Path, name: str) -> dict:
    """Host synchronisations per step and the top CUDA kernels over `n` calls of `step()`."""
    from torch.profiler import ProfilerActivity, profile

    step()
    sync()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(n):
            step()
        sync()
    avg = prof.key_averages()
    counts = {e.key: e.count / n for e in avg if e.key in SYNC_OPS}
    dtoh = sum(e.count for e in avg if "Memcpy DtoH" in e.key) / n
    counts["Memcpy DtoH (device)"] = dtoh
    (out / f"profile_{name}.txt").write_text(avg.table(sort_by="cuda_time_total", row_limit=30))
    return {k: round(v, 2) for k, v in counts.items()}


# -- ours ---------------------------------------------------------------------------------------
def run_ours(capture, frame, views, model0, config, out: Path, args) -> dict:
    sched = config.schedule
    clock = StageClock({sched.stage2_start, sched.stage3_start})
    reset_peak()
    t0 = time.perf_counter()
    # A copy: the trainer grows and prunes its model in place, and every system starts from
    # the same initial Gaussians (before 2026-11-27 the systems after ours started from ours'
    # trained model, on a CUDA device where `to` returns the model itself).
    start = GaussianModel({k: v.detach().clone() for k, v in model0.params.items()})
    trainer = Trainer(views, config, model=start, callbacks=[clock])
    trainer.train()
    sync()
    seconds = time.perf_counter() - t0
    stages = clock.table()
    if trainer.ao_seconds and "stage 3" in stages:  # the bake is in stage 3's first step
        s3 = stages["stage 3"]
        s3["steps_per_s"] = round(s3["steps"] / max(s3["seconds"] - trainer.ao_seconds, 1e-9), 2)
    res = {"stages": stages, "seconds": round(seconds, 2),
           "ao_bake_seconds": None if trainer.ao_seconds is None else round(trainer.ao_seconds, 2),
           "peak_gb": peak_gb(),
           "gaussians": len(trainer.model)}
    model, p = trainer.current()
    bg = trainer.background

    def draw(cam):
        rc = RenderCamera.from_camera(cam, device=trainer.device, near=trainer.near)
        r = render(model, rc, sh_degree=p.sh_degree, beta=p.beta, geometry=True,
                   tie_opacity=p.tie_opacity, background=bg, eps2d=config.eps2d,
                   antialiased=config.antialiased)
        n = torch.nn.functional.normalize(r.normal, dim=-1)
        return r.rgb, n, r.alpha_g[..., 0] > COVERAGE

    t = time.perf_counter()
    res["held_out"] = held_out(capture, frame, args.downscale, draw, bg.cpu().numpy())
    res["eval_seconds"] = round(time.perf_counter() - t, 2)
    res["_trainer"] = trainer
    return res


def bake_parts(trainer) -> dict:
    """The AO bake of the final model again, its parts timed (device synchronized between):
    the views' quarter-resolution renders (the ray origins), the trace (tree build and rays),
    the per-view maps (upsampling and the joint bilateral filter)."""
    from core.ao import _map, _origins, _trace
    from native import gaussian_rays

    model, p = trainer.current()
    cfg, cams = trainer.config.ao, trainer.cameras
    out, t = {}, time.perf_counter()

    def lap(name):
        nonlocal t
        sync()
        now = time.perf_counter()
        out[name] = round(now - t, 3)
        t = now
    with torch.no_grad():
        views = [_origins(model, cam, p.beta, cfg) for cam in cams]
        lap("origins (renders) s")
        means = model.means.detach()
        own_offset, own_exclude = gaussian_rays(means, model.scales)
        origins = torch.cat([means] + [o.points for o in views])
        normals = torch.cat([model.normals.detach()] + [o.normals for o in views])
        offset = torch.cat([own_offset] + [o.offset for o in views])
        exclude = torch.cat([own_exclude, torch.full((origins.shape[0] - len(model),), -1,
                                                     device=means.device)])
        lap("gather s")
        vis = _trace(model, origins, normals, offset, exclude, cfg)
        lap("trace s")
        parts = vis[len(model):].split([o.points.shape[0] for o in views])
        for o, v, cam in zip(views, parts, cams):
            _map(o, v, cam, cfg)
        lap("maps s")
    out["rays"] = int(origins.shape[0])
    out["gaussians"] = len(model)
    return out


# -- gsplat -------------------------------------------------------------------------------------
def gsplat_resets(gsplat) -> bool:
    """Whether the installed gsplat's `DefaultStrategy` resets opacities at its reset steps:
    released 1.5.3 never does (its condition `step % reset_every == 0 & step > 0` is a chained
    comparison with 0 > 0; gsplat pull request 776 fixed it after that release). Probed on one
    CPU Gaussian at step 1 with a reset every step."""
    strategy = gsplat.DefaultStrategy(refine_start_iter=10**9, refine_stop_iter=10,
                                      reset_every=1)
    params = torch.nn.ParameterDict({k: torch.zeros(1, n) for k, n in
                                     (("means", 3), ("scales", 3), ("quats", 4))})
    params["quats"].data[:, 0] = 1
    params["opacities"] = torch.nn.Parameter(torch.full((1,), 5.0))
    optimizers = {k: torch.optim.Adam([params[k]]) for k in params}
    means2d = torch.zeros(1, 2, requires_grad=True)
    means2d.grad = torch.zeros(1, 2)
    info = {"width": 1, "height": 1, "n_cameras": 1, "radii": torch.ones(1, 2),
            "gaussian_ids": torch.zeros(1, dtype=torch.long), "means2d": means2d}
    strategy.step_post_backward(params, optimizers, strategy.initialize_state(), 1, info,
                                packed=True)
    return float(torch.sigmoid(params["opacities"].detach())[0]) < 0.5


class GsplatTrainer:
    """A plain 3DGS on gsplat's API (module docstring), from our initial model. `reset`: the
    opacity resets of 3DGS, made here when the installed strategy skips them (gsplat 1.5.3);
    off, the installed strategy as it is."""

    def __init__(self, views, model0: GaussianModel, steps: int, extent: float, background,
                 seed: int, reset: bool = False):
        import gsplat

        self.gsplat = gsplat
        self.installed_resets = gsplat_resets(gsplat)
        self.own_resets = reset and not self.installed_resets
        dev = torch.device("cuda")
        self.views, self.steps, self.background = views, steps, background
        f = steps / 30_000
        p = model0.params
        self.params = torch.nn.ParameterDict({
            "means": p["means"].detach().clone(), "scales": p["scales"].detach().clone(),
            "quats": p["quats"].detach().clone(), "opacities": p["opacity_c"].detach().clone(),
            "sh0": p["sh0"].detach().clone(), "shN": p["shN"].detach().clone()}).to(dev)
        rates = {"means": 1.6e-4 * extent, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2,
                 "sh0": 2.5e-3, "shN": 2.5e-3 / 20}  # gsplat simple_trainer / 3DGS
        self.optimizers = {k: torch.optim.Adam([{"params": self.params[k], "lr": lr, "name": k}],
                                               eps=1e-15)
                           for k, lr in rates.items()}
        self.decay = torch.optim.lr_scheduler.ExponentialLR(self.optimizers["means"],
                                                            gamma=0.01 ** (1.0 / steps))
        self.strategy = gsplat.DefaultStrategy(
            refine_start_iter=max(1, round(500 * f)), refine_stop_iter=max(2, round(15_000 * f)),
            reset_every=max(1, round(3000 * f)), refine_every=max(1, round(100 * f)))
        self.strategy.check_sanity(self.params, self.optimizers)
        self.state = self.strategy.initialize_state(scene_scale=extent)
        self.sh_interval = max(1, round(1000 * f))
        self.cams = [RenderCamera.from_camera(v.camera, device=dev) for v in views]
        self.generator = torch.Generator().manual_seed(seed)
        self.order: list[int] = []
        self.step = 0

    def draw(self, cam: RenderCamera, sh_degree: int, mode: str = "RGB"):
        P = self.params
        colors = torch.cat([P["sh0"], P["shN"]], 1)
        img, alpha, info = self.gsplat.rasterization(
            P["means"], P["quats"], torch.exp(P["scales"]), torch.sigmoid(P["opacities"]),
            colors, cam.viewmat[None], cam.K[None], cam.width, cam.height, sh_degree=sh_degree,
            rasterize_mode="classic", packed=True, render_mode=mode)
        rgb = img[0, ..., :3] + (1 - alpha[0]) * self.background
        if mode == "RGB":
            return rgb, info
        return rgb, img[0, ..., 3:4], alpha[0]

    def draw_normals(self, cam: RenderCamera):
        """Colour, and normals from the expected depth's central differences (a plain 3DGS
        has no normals of its own: this is how one gets them, as in 2DGS's and PGSR's
        comparisons), covered where its alpha passes the pictures' threshold."""
        rgb, depth, alpha = self.draw(cam, 3, "RGB+ED")
        inner = depth_to_normals(depth, cam.K, cam.viewmat)
        normal = torch.nn.functional.pad(inner.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)
        return rgb, normal, alpha[..., 0] > COVERAGE

    def train_step(self) -> None:
        if not self.order:
            self.order = torch.randperm(len(self.views), generator=self.generator).tolist()
        i = self.order.pop()
        img, info = self.draw(self.cams[i], min(3, self.step // self.sh_interval))
        self.strategy.step_pre_backward(self.params, self.optimizers, self.state, self.step,
                                        info)
        loss = photometric_loss(img, self.views[i].image)
        loss.backward()
        for opt in self.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        self.decay.step()
        self.strategy.step_post_backward(self.params, self.optimizers, self.state, self.step,
                                         info, packed=True)
        st = self.strategy
        if self.own_resets and 0 < self.step < st.refine_stop_iter \
                and self.step % st.reset_every == 0:
            from gsplat.strategy.ops import reset_opa

            reset_opa(self.params, self.optimizers, self.state, value=st.prune_opa * 2.0)
        self.step += 1

    def train(self, clock: StageClock) -> None:
        clock.start()
        while self.step < self.steps:
            self.train_step()
            clock.count("plain", self.step - 1, self.step == self.steps)


def run_gsplat(capture, frame, views, model0, steps, extent, background, args,
               reset: bool = False) -> dict:
    clock = StageClock()
    reset_peak()
    t0 = time.perf_counter()
    g = GsplatTrainer(views, model0, steps, extent, background, args.seed, reset)
    g.train(clock)
    seconds = time.perf_counter() - t0
    res = {"stages": clock.table(), "seconds": round(seconds, 2),
           "peak_gb": peak_gb(),
           "gaussians": int(g.params["means"].shape[0]),
           "gsplat": g.gsplat.__version__, "installed_strategy_resets": g.installed_resets,
           "resets_made_here": g.own_resets}

    def draw(cam):
        return g.draw_normals(RenderCamera.from_camera(cam, device="cuda"))

    res["held_out"] = held_out(capture, frame, args.downscale, draw,
                               background.cpu().numpy())
    res["_trainer"] = g
    return res


# -- the run ------------------------------------------------------------------------------------
def open_capture(src: Path, work: Path):
    if (src / "capture.json").is_file():
        return load_capture(src)
    t = time.perf_counter()
    cap = import_capture(src, work / "capture")
    print(f"imported {src.name} in {time.perf_counter() - t:.1f} s", flush=True)
    return cap


def save(report: dict, out: Path) -> None:
    clean = {k: ({kk: vv for kk, vv in v.items() if not kk.startswith("_")}
                 if isinstance(v, dict) else v) for k, v in report.items()}
    (out / "result.json").write_text(json.dumps(clean, indent=2, default=str))


def part(report: dict, out: Path, name: str, fn):
    t = time.perf_counter()
    try:
        report[name] = fn()
    except Exception as exc:  # noqa: BLE001  (a benchmark part fails alone; the rest still run)
        traceback.print_exc()
        report[name] = {"error": f"{type(exc).__name__}: {exc}"[:2000]}
    print(f"[{name}] {time.perf_counter() - t:.1f} s", flush=True)
    save(report, out)
    return report[name]


def table(report: dict) -> str:
    lines = ["| system | s (frame) | stage s (steps/s) | AO bake s | peak GB | Gaussians | "
             "held-out PSNR | SSIM | normals deg |", "|---|---|---|---|---|---|---|---|---|"]
    for name in SYSTEMS:
        r = report.get(name)
        if r is None:
            continue
        if "error" in r:
            lines.append(f"| {name} | {r and r.get('error', '')[:80]} |||||||")
            continue
        st = "; ".join(f"{k} {v['seconds']:.1f} ({v['steps_per_s']:.0f})"
                       for k, v in r["stages"].items())
        h = r["held_out"]
        nd = h.get("normal_deg")
        lines.append(f"| {name} | {r['seconds']:.1f} | {st} | {r.get('ao_bake_seconds') or '-'} | "
                     f"{r['peak_gb']:.2f} | {r['gaussians']} | {h['psnr_full']:.2f} | "
                     f"{h['ssim']:.4f} | {'-' if nd is None else f'{nd:.2f}'} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--frame", default=None)
    ap.add_argument("--systems", nargs="+", default=["ours", "gsplat"], choices=SYSTEMS)
    ap.add_argument("--seed", type=int, default=0,
                    help="training seed of every system (the initial points do not change)")
    ap.add_argument("--profile-steps", type=int, default=20)
    ap.add_argument("--mesh-voxels", type=int, default=512)
    ap.add_argument("--seed-file", type=Path, default=None,
                    help="initial points (.npz): read when it exists, else made and written")
    ap.add_argument("--device", default="cuda", help="cpu: a smoke test of ours (no gsplat)")
    args = ap.parse_args()
    dev = args.device
    if dev.startswith("cuda") and not torch.cuda.is_available():
        print("needs a CUDA device (or --device cpu for a smoke test of ours)", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="dgs-keyframe-"))
    report: dict = {"device": torch.cuda.get_device_name() if dev != "cpu" else "cpu",
                    "torch": torch.__version__,
                    "cuda": torch.version.cuda, "steps": args.steps,
                    "downscale": args.downscale, "seed": args.seed}
    t = time.perf_counter()
    capture = open_capture(args.capture, work)
    frame = args.frame or next(iter(capture.frames))
    config = replace(train_config("paper").stretched(args.steps / 30_000), device=dev)
    selected = select_views(capture, downscale=args.downscale)
    views = [v.to(dev) for v in frame_views(capture, frame, selected)]
    if args.seed_file is not None and args.seed_file.is_file():
        z = np.load(args.seed_file)
        points, colors, note = (torch.from_numpy(z["points"]), torch.from_numpy(z["colors"]),
                                str(z["note"]) + " (read from the seed file)")
    else:
        seed = seed_points([v.camera for v in views], [v.image.cpu().numpy() for v in views],
                           [None if v.mask is None else v.mask.cpu().numpy() for v in views],
                           config.init, n_random=config.init_points, seed=config.seed)
        points, colors, note = seed.points, seed.colors, seed.note
        if args.seed_file is not None:
            np.savez(args.seed_file, points=points.numpy(), colors=colors.numpy(), note=note)
    model0 = GaussianModel.from_points(points.to(dev), colors.to(dev))
    # `--seed` is every system's training seed (view order, densification draws); the initial
    # points above come from the preset's fixed seed (or the seed file), the same for every S.
    config = replace(config, seed=args.seed)
    extent = scene_extent([v.camera for v in views])
    report["setup"] = {"seconds": round(time.perf_counter() - t, 2), "views": len(views),
                       "resolution": list(views[0].image.shape[:2]), "seed": note,
                       "initial_gaussians": len(model0)}
    print(json.dumps(report["setup"]), flush=True)
    background = torch.tensor(config.background, dtype=torch.float32, device=dev)
    if "ours" in args.systems:
        part(report, args.out, "ours",
             lambda: run_ours(capture, frame, views, model0, config, args.out, args))
    if "ours-3dgs" in args.systems:
        plain = method_defaults(config, "3dgs")
        part(report, args.out, "ours-3dgs",
             lambda: run_ours(capture, frame, views, model0, plain, args.out, args))
    for name in ("gsplat", "gsplat-3dgs"):
        if name in args.systems:
            part(report, args.out, name,
                 lambda name=name: run_gsplat(capture, frame, views, model0, args.steps, extent,
                                              background, args, reset=name == "gsplat-3dgs"))
    print(table(report), flush=True)
    for name in ("ours", "gsplat"):
        tr = (report.get(name) or {}).get("_trainer")
        if name == "ours" and tr is not None:  # profile steps inside stage 3 (they train on)
            tr.step = max(config.schedule.stage3_start + 1, tr.iterations - args.profile_steps - 2)
        if tr is not None and args.profile_steps:
            part(report, args.out, f"{name}_host_syncs",
                 lambda tr=tr, name=name: host_syncs(tr.train_step, args.profile_steps,
                                                     args.out, name))
    ours = (report.get("ours") or {}).get("_trainer")
    if ours is not None and ours.config.bake_ao:
        part(report, args.out, "bake_parts", lambda: bake_parts(ours))
    if ours is not None and args.mesh_voxels:
        from core.config import MeshConfig
        from core.mesh.build import mesh_model

        def mesh():
            model, p = ours.current()
            settings = SimpleNamespace(sh_degree=p.sh_degree, beta=p.beta, eps2d=config.eps2d,
                                       antialiased=config.antialiased)
            sync()
            t0 = time.perf_counter()
            _, info = mesh_model(model, [v.camera for v in views], settings,
                                 MeshConfig(resolution=args.mesh_voxels, device=dev))
            sync()
            return {**info, "wall_seconds": round(time.perf_counter() - t0, 2)}
        part(report, args.out, "mesh", mesh)
    print(json.dumps({k: v for k, v in report.items() if k.endswith("host_syncs")
                      or k in ("mesh", "bake_parts")}, default=str), flush=True)
    print(table(report), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
