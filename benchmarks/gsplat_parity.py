"""Is our plain 3DGS gsplat's? (issue 30) Two checks against gsplat's own code, read from a
gsplat source checkout (only pure-PyTorch modules: no CUDA build, no package import):

- `render`: one view of a random scene through our rasterizer in 3DGS's classic mode (0.3 px
  blur, no compensation) and through gsplat's PyTorch reference (`cuda/_torch_impl.py`: its
  projection, covariance and conics; the compositing of its `rasterize_to_pixels` written out
  densely with its rules: pixel centres at +0.5, alpha = min(0.99, o exp(-sigma)), skipped
  below 1/255, stopped before the transmittance would fall to 1e-4): the image, the projected
  centres and the gradients of an L1 loss (view-space means, which drive densification; means,
  scales, opacities, colours) compared;
- `densify`: one training run of `train.method` 3dgs on a capture, with gsplat's own
  `DefaultStrategy` (`strategy/default.py`, `ops.py`) shadowing ours: after every step its
  `_update_state` takes the same rasterizer output (view-space gradients, radii) as our
  `DensifyStrategy.update`, and at every densification the Gaussians each would grow are
  compared before ours acts, and gsplat's own `_grow_gs` and `_prune_gs` are run on a copy of
  our model to compare the count they leave (it does not depend on where split samples land).

Equal renders and gradients, equal selections at every event and equal counts mean the two
trainers do the same arithmetic from the same renders: a gap between their Gaussian counts or
PSNR then comes from the run (split samples, view order, the GPU's float atomics), not from
the method.

    python benchmarks/gsplat_parity.py CAPTURE --gsplat GSPLAT_SRC [--parts render densify]
                                       [--downscale 16] [--steps 1500] [--threads 1]

GSPLAT_SRC is a folder holding gsplat's package (`GSPLAT_SRC/gsplat/strategy/default.py`), e.g.
a `git archive` of github.com/nerfstudio-project/gsplat.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import types
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import core  # noqa: E402,F401  (OpenMP's wait policy before torch)


def _stub(name: str, **attrs) -> types.ModuleType:
    module = types.ModuleType(name)
    for key, value in attrs.items():
        setattr(module, key, value)
    sys.modules[name] = module
    return module


def _load(name: str, path: Path) -> types.ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def gsplat_modules(src: Path) -> tuple[types.ModuleType, types.ModuleType, type]:
    """gsplat's `cuda/_math.py`, `cuda/_torch_impl.py` and `DefaultStrategy` from its source,
    without importing the package (whose `__init__` builds the CUDA extension): stand-ins for
    the names they import that these checks never call, and for the one they do (a split's
    quaternion to rotation matrix: ours, the same formula)."""
    from native.reference import quat_to_rotmat

    root = src / "gsplat"
    for need in ("strategy/default.py", "cuda/_torch_impl.py"):
        if not (root / need).is_file():
            raise SystemExit(f"--gsplat: {src} holds no gsplat/{need}")
    _stub("gsplat", __path__=[str(root)], quat_scale_to_covar_preci=None)
    _stub("gsplat.cuda", __path__=[str(root / "cuda")])
    _stub("gsplat.cuda._wrapper", CameraModel=str, RollingShutterType=None)
    _stub("gsplat.relocation", compute_relocation=None)
    _stub("gsplat.utils", normalized_quat_to_rotmat=quat_to_rotmat)
    _stub("gsplat.strategy", __path__=[str(root / "strategy")])
    _load("gsplat._helper", root / "_helper.py")
    _load("gsplat.cuda._constants", root / "cuda" / "_constants.py")
    maths = _load("gsplat.cuda._math", root / "cuda" / "_math.py")
    reference = _load("gsplat.cuda._torch_impl", root / "cuda" / "_torch_impl.py")
    for name in ("base", "ops"):
        _load(f"gsplat.strategy.{name}", root / "strategy" / f"{name}.py")
    default = _load("gsplat.strategy.default", root / "strategy" / "default.py")
    return maths, reference, default.DefaultStrategy


def render_part(views, maths, reference, n: int = 1500, seed: int = 0) -> dict:
    """The `render` check (module docstring) on `n` Gaussians spread over the view of
    `views[3]`'s camera, 1 to 3 units in front of it."""
    import torch

    import native
    from core.render import RenderCamera

    g = torch.Generator().manual_seed(seed)
    cam = RenderCamera.from_camera(views[min(3, len(views) - 1)].camera)
    W, H, K = cam.width, cam.height, cam.K
    z = torch.rand(n, generator=g) * 2 + 1
    x = (torch.rand(n, generator=g) * W - K[0, 2]) / K[0, 0] * z
    y = (torch.rand(n, generator=g) * H - K[1, 2]) / K[1, 1] * z
    local = torch.stack([x, y, z, torch.ones(n)], 1)
    leaves = {
        "means": (torch.linalg.inv(cam.viewmat) @ local.T).T[:, :3].contiguous(),
        "quats": torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
        "scales": torch.randn(n, 3, generator=g) * 0.5 - 4.0,
        "opacities": torch.randn(n, generator=g) * 2,
        "colors": torch.rand(n, 3, generator=g)}
    target, bg = torch.rand(H, W, 3, generator=g), torch.tensor([0.1, 0.2, 0.3])

    def ours(p):
        o = torch.sigmoid(p["opacities"])
        out = native.rasterize(p["means"], p["quats"], torch.exp(p["scales"]), o, o,
                               p["colors"], None, cam.viewmat, K, W, H, beta=0.0, eps2d=0.3,
                               antialiased=False, background=bg)
        return out.color, out.means2d

    def theirs(p):
        o = torch.sigmoid(p["opacities"])
        covars, _ = maths._quat_scale_to_covar_preci(p["quats"], torch.exp(p["scales"]),
                                                     compute_preci=False, triu=False)
        radii, m2d, depths, conics, _ = reference._fully_fused_projection(
            p["means"], covars, cam.viewmat[None], K[None], W, H, eps2d=0.3)
        m2d.retain_grad()
        m, c, drawn = m2d[0], conics[0], (radii[0] > 0).all(-1)
        order = torch.argsort(depths[0])
        order = order[drawn[order]]
        ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
        d = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)[None] - m[order][:, None]
        c = c[order]
        sigma = (0.5 * (c[:, 0:1] * d[..., 0] ** 2 + c[:, 2:3] * d[..., 1] ** 2)
                 + c[:, 1:2] * d[..., 0] * d[..., 1])
        alpha = torch.clamp_max(o[order][:, None] * torch.exp(-sigma), 0.99)
        alpha = torch.where((alpha >= 1 / 255) & (sigma >= 0), alpha, torch.zeros_like(alpha))
        after = torch.cumprod(1 - alpha, 0)
        before = torch.cat([torch.ones_like(after[:1]), after[:-1]])
        kept = after > 1e-4
        rest = torch.where(kept, after, torch.ones_like(after)).amin(0)
        image = ((alpha * before * kept)[..., None] * p["colors"][order][:, None]).sum(0) \
            + rest[:, None] * bg
        return image.reshape(H, W, 3), m2d

    got = {}
    for name, draw in (("ours", ours), ("gsplat", theirs)):
        p = {k: v.clone().requires_grad_() for k, v in leaves.items()}
        image, m2d = draw(p)
        (image - target).abs().mean().backward()
        got[name] = {"image": image.detach(), "centres": m2d.detach().reshape(-1, 2),
                     "view-space means": m2d.grad.reshape(-1, 2),
                     **{k: v.grad for k, v in p.items()}}
    a, b = got["ours"], got["gsplat"]
    row = {"gaussians": n, "size": f"{W}x{H}",
           "image": float((a["image"] - b["image"]).abs().max()),
           "centres": float((a["centres"] - b["centres"]).abs().max())}
    for key in ("view-space means", "means", "scales", "opacities", "colors"):
        row[key] = float((a[key] - b[key]).norm() / b[key].norm().clamp_min(1e-30))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture", type=Path)
    ap.add_argument("--gsplat", type=Path, required=True, help="gsplat's source folder")
    ap.add_argument("--parts", nargs="+", choices=("render", "densify"),
                    default=["render", "densify"])
    ap.add_argument("--downscale", type=float, default=16.0)
    ap.add_argument("--steps", type=int, default=1500, help="the fast preset scaled to N steps")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args()
    maths, reference, DefaultStrategy = gsplat_modules(args.gsplat)

    import torch

    from core.config import select_views, train_config
    from core.data import load_capture
    from core.training import Trainer
    from core.training.views import frame_views

    if args.threads:
        torch.set_num_threads(args.threads)
    capture = load_capture(args.capture)
    views = frame_views(capture, next(iter(capture.frames)),
                        select_views(capture, downscale=args.downscale))
    if "render" in args.parts:
        row = render_part(views, maths, reference, seed=args.seed)
        print(f"\nrenders: {row['gaussians']} Gaussians, {row['size']} px; largest absolute "
              "difference of the image and of the projected centres (px), relative difference "
              "(norm) of each gradient\n")
        keys = [k for k in row if k not in ("gaussians", "size")]
        print("| " + " | ".join(keys) + " |")
        print("|" + "---|" * len(keys))
        print("| " + " | ".join(f"{row[k]:.1e}" for k in keys) + " |", flush=True)
    if "densify" not in args.parts:
        return
    config = replace(train_config("fast", "3dgs").stretched(args.steps / 7_500), seed=args.seed)
    s = config.schedule
    theirs = DefaultStrategy(refine_start_iter=s.densify_from, refine_stop_iter=s.densify_until,
                             reset_every=s.reset_interval, refine_every=s.densify_interval)
    events: list[dict] = []

    class Shadowed(Trainer):
        """Our trainer, feeding each step's render to gsplat's statistics as well."""

        shadow: dict | None = None

        def after_step(self, r, index, p):
            if self.shadow is None:
                self.shadow = theirs.initialize_state(scene_scale=self.extent)
            cam, raster = self.cameras[index], r.raster
            ids = (raster.radii > 0).nonzero()[:, 0]
            info = {"width": cam.width, "height": cam.height, "n_cameras": 1,
                    "radii": raster.radii[ids][:, None].repeat(1, 2).float(),
                    "gaussian_ids": ids,
                    "means2d": types.SimpleNamespace(grad=raster.means2d.grad[ids].clone())}
            if self.step < s.densify_until:  # gsplat updates only inside its refine window
                theirs._update_state({"means": self.model.params["means"]}, self.shadow, info,
                                     packed=True)
            super().after_step(r, index, p)
            if p.densify or p.reset_opacity:  # both start their statistics again
                self.shadow = None

    trainer = Shadowed(views, config)
    ours = trainer.strategy.densify

    def compared(model, optimizer, state, generator=None, tied=False):
        with torch.no_grad():
            count = trainer.shadow["count"]
            grads = trainer.shadow["grad2d"] / count.clamp_min(1)
            picked = grads > theirs.grow_grad2d
            mine, _ = trainer.strategy._selection(model, state)
            own = state.grad_c / state.count.clamp_min(1)
            events.append({
                "step": trainer.step, "n": len(model), "theirs": int(picked.sum()),
                "ours": int(mine.sum()), "same": bool((picked == mine).all()),
                "count": float((count - state.count).abs().max()),
                "grad": float((grads - own).abs().max() / own.abs().max().clamp_min(1e-12))})
        return ours(model, optimizer, state, generator, tied)

    def grown_by_theirs(model) -> int:
        """The Gaussians gsplat's own grow and prune leave, run on a copy of ours (their count
        does not depend on where the split samples land)."""
        with torch.no_grad():
            params = torch.nn.ParameterDict({
                "means": model.params["means"].detach().clone(),
                "scales": model.params["scales"].detach().clone(),
                "quats": model.params["quats"].detach().clone(),
                "opacities": model.params["opacity_c"].detach().clone()})
            optimizers = {k: torch.optim.Adam([{"params": params[k], "lr": 0.0, "name": k}])
                          for k in params}
            state = {k: (v.clone() if torch.is_tensor(v) else v)
                     for k, v in trainer.shadow.items()}
            theirs._grow_gs(params, optimizers, state, trainer.step)
            theirs._prune_gs(params, optimizers, state, trainer.step)
            return len(params["means"])

    def checked(model, optimizer, state, generator=None, tied=False):
        expected = grown_by_theirs(model)
        record = compared(model, optimizer, state, generator, tied)
        events[-1]["after"] = (record["n"], expected)
        return record

    trainer.strategy.densify = checked
    trainer.train()
    same = sum(e["same"] for e in events)
    equal = sum(e["after"][0] == e["after"][1] for e in events)
    print(f"\ndensification: {args.capture} at 1/{args.downscale:g}, {args.steps} steps, "
          f"{len(views)} training views, seed {args.seed}\n")
    print("| densifications | same selection | same count after grow and prune | "
          "largest view-count difference | largest mean-gradient difference (relative) | "
          "selected by ours / gsplat's (sum) | Gaussians at the end |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {len(events)} | {same} | {equal} | {max(e['count'] for e in events):g} | "
          f"{max(e['grad'] for e in events):.2e} | {sum(e['ours'] for e in events)} / "
          f"{sum(e['theirs'] for e in events)} | {len(trainer.model)} |")


if __name__ == "__main__":
    main()
