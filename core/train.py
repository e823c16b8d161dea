"""Static reconstruction of one frame: the staged schedule, losses and densification put together.

`Trainer` runs the loop; what happens around it (progress, checkpoints) comes in through small
callback objects (in the manner of nerfstudio's engine/callbacks.py). Ambient-occlusion baking is
a hook (`AOBaker`, by default `core.ao.GaussianAOBaker` on the native ray tracer) called at the
step the schedule names; with `bake_ao` off the visibility loss stays off and the trainer records
that baking was skipped.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Protocol, TextIO

import torch
from torch import Tensor

from core.data.capture import Camera
from core.data.points import PointCloud
from core.device import check_device_spec, resolve_device, to_device
from core.losses import (
    LossWeights,
    depth_normal_consistency,
    geometry_mask_loss,
    normal_prior_loss,
    photometric_loss,
    visibility_loss,
)
from core.model import GaussianModel, LearningRates, means_lr
from core.render import RenderCamera, render
from core.seeding import InitConfig, scene_extent, seed_points
from core.stages import Schedule, StagePlan, plan, schedule_for
from core.strategy import DensifyConfig, DensifyStrategy, StrategyState

__all__ = [
    "AOBaker",
    "Callback",
    "CheckpointCallback",
    "ProgressCallback",
    "StepInfo",
    "TrainConfig",
    "Trainer",
    "View",
    "psnr",
    "train_config",
    "training_cameras",
]


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides how one frame is reconstructed."""

    schedule: Schedule = field(default_factory=Schedule)
    """Stage boundaries, beta ramp, densification and reset timing."""
    rates: LearningRates = field(default_factory=LearningRates)
    """Adam learning rates per parameter group."""
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    """Densification and pruning thresholds."""
    losses: LossWeights = field(default_factory=LossWeights)
    """Loss weights."""
    init_points: int = 100_000
    """Random initial points where neither the capture nor triangulation gives any; with masks,
    the visual hull is filled with random points up to this many seeds."""
    init: InitConfig = field(default_factory=InitConfig)
    """Where the initial points come from (the capture's points.ply, triangulation, random)."""
    eps2d: float = 0.1
    """Screen-space blur of the Mip-Splatting 2D filter (DESIGN.md section 5)."""
    antialiased: bool = True
    """Apply the Mip-Splatting opacity compensation."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Colour behind the Gaussians; masked-out target pixels take it too."""
    random_background: bool = True
    """Views with a mask train in front of a new uniformly random colour each step (render and
    target alike), so the rendered coverage must match the mask: against a fixed background, a
    Gaussian of the background's colour costs nothing where the mask says background and floats
    into held-out views (3DGS trains masked synthetic scenes the same way, --random_background).
    Views without a mask always use `background`."""
    seed: int = 0
    """Seeds initial points, view order and split samples."""
    bake_ao: bool = True
    """Bake ambient occlusion at the stage-3 step with the native ray tracer (per-Gaussian
    visibility and per-view targets); off: the visibility loss stays off."""
    device: str = "auto"
    """Where training runs: `auto` (CUDA when torch sees a GPU and the native extension has its
    CUDA kernels, else the CPU; $DGS_DEVICE when set), `cpu`, `cuda` or `cuda:N`
    (`core.device.resolve_device`).
    RUN/config.json records the device the run resolved to; a run resumes on any device."""

    def __post_init__(self) -> None:
        if self.init_points < 1:
            raise ValueError(f"init_points: expected >= 1, got {self.init_points}")
        check_device_spec(self.device)

    def to_dict(self) -> dict:
        """The fully resolved configuration as JSON-compatible data (for RUN/config.json)."""
        return asdict(self)


def train_config(preset: str) -> TrainConfig:
    """Named presets: `paper` (30k steps), `fast` (7.5k) and `test` (500, tiny captures)."""
    schedule = schedule_for(preset)
    if preset == "paper":
        return TrainConfig(schedule=schedule)
    if preset == "fast":
        return TrainConfig(schedule=schedule, init_points=50_000,
                           rates=replace(LearningRates(), means_decay_steps=schedule.iterations))
    return TrainConfig(schedule=schedule, init_points=1_000,
                       rates=replace(LearningRates(), means_decay_steps=schedule.iterations),
                       densify=replace(DensifyConfig(), max_gaussians=4_000))


def training_cameras(cameras: Sequence[Camera]) -> list[Camera]:
    """Every camera except the held-out ones (index % 8 == 0, DESIGN.md section 3.2)."""
    return [c for i, c in enumerate(cameras) if i % 8 != 0]


@dataclass
class View:
    """One training view in memory: camera and (H, W, C) tensors."""

    camera: Camera
    image: Tensor
    mask: Tensor | None = None
    normal: Tensor | None = None

    @classmethod
    def from_sample(cls, sample) -> View:
        """From a `core.data.Sample`."""
        return cls(sample.camera, sample.image, sample.mask, sample.normal)

    def to(self, device: torch.device | str) -> View:
        """This view with its tensors on `device` (itself when they are there already): a
        trainer moves each view once, not every step."""
        moved = [None if t is None else t.to(device) for t in (self.image, self.mask,
                                                                 self.normal)]
        if all(a is b for a, b in zip(moved, (self.image, self.mask, self.normal))):
            return self
        return View(self.camera, *moved)


class AOBaker(Protocol):
    """Bakes visibility: per-Gaussian values written into the model (through the optimizer, so
    Adam's moments follow), per-view target maps (H, W, 1) returned. The default is
    `core.ao.GaussianAOBaker` (the native ray tracer)."""

    def __call__(self, model: GaussianModel, cameras: Sequence[RenderCamera],
                 optimizer: torch.optim.Optimizer, beta: float) -> list[Tensor]: ...


@dataclass
class StepInfo:
    """What a callback sees after each step."""

    step: int
    plan: StagePlan
    losses: dict[str, float]
    n_gaussians: int
    seconds: float
    psnr: float | None = None
    """PSNR (dB) of this step's training render against its target, both on the configured
    background (comparable between steps whatever the step's random background)."""


class Callback:
    """Hooks around training; override what you need."""

    def on_train_start(self, trainer: Trainer) -> None: ...

    def on_step_end(self, trainer: Trainer, info: StepInfo) -> None: ...

    def on_train_end(self, trainer: Trainer) -> None: ...


class ProgressCallback(Callback):
    """Prints (or hands to `report`) a line every `every` steps."""

    def __init__(self, every: int = 100, stream: TextIO | None = None,
                 report: Callable[[StepInfo], None] | None = None):
        if every < 1:
            raise ValueError(f"every: expected >= 1, got {every}")
        self.every, self.stream, self.report = every, stream, report

    def on_step_end(self, trainer: Trainer, info: StepInfo) -> None:
        last = info.step == trainer.config.schedule.iterations - 1
        if info.step % self.every and not last:
            return
        if self.report is not None:
            self.report(info)
            return
        print(f"step {info.step + 1}/{trainer.config.schedule.iterations} stage {info.plan.stage} "
              f"loss {info.losses['total']:.4f} gaussians {info.n_gaussians} "
              f"{info.seconds:.1f}s", file=self.stream or sys.stdout)


class CheckpointCallback(Callback):
    """Writes `folder/<filename>` (atomically) every `every` steps and at the end; `extra`
    (a callable returning plain data) is stored beside the training state; `on_saved(path)` runs
    once the file is complete on disk (a service copies it off the machine there, so that a
    crashed worker's successor can resume from it)."""

    def __init__(self, folder: str | os.PathLike[str], every: int = 1000,
                 filename: str = "checkpoint.pt", extra: Callable[[], object] | None = None,
                 on_saved: Callable[[Path], None] | None = None):
        if every < 1:
            raise ValueError(f"every: expected >= 1, got {every}")
        self.folder, self.every, self.filename, self.extra = Path(folder), every, filename, extra
        self.on_saved = on_saved

    def save(self, trainer: Trainer) -> Path:
        """Write the checkpoint now; returns its path."""
        path = self.folder / self.filename
        trainer.save_checkpoint(path, extra=None if self.extra is None else self.extra())
        if self.on_saved is not None:
            self.on_saved(path)
        return path

    def on_step_end(self, trainer: Trainer, info: StepInfo) -> None:
        if (info.step + 1) % self.every == 0:
            self.save(trainer)

    def on_train_end(self, trainer: Trainer) -> None:
        self.save(trainer)


def psnr(pred: Tensor, target: Tensor) -> float:
    """Peak signal-to-noise ratio (dB) of images in 0..1."""
    mse = float((pred.detach() - target).square().mean())
    return 100.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


class Trainer:
    """Reconstructs one frame from its training views, on `config.device`: the model, the
    optimizer state, the views' images, masks and priors, the cameras and the AO targets all
    live there. The random generator stays on the CPU (its draws are moved), so a run draws the
    same numbers on any device and its state resumes anywhere."""

    def __init__(self, views: Sequence[View], config: TrainConfig = TrainConfig(), *,
                 model: GaussianModel | None = None, callbacks: Sequence[Callback] = (),
                 ao_baker: AOBaker | None = None, points: PointCloud | None = None):
        if not views:
            raise ValueError("views: expected at least one training view")
        self.config = config
        self.device = resolve_device(config.device, "config.device")
        self.views = [v.to(self.device) for v in views]
        self.callbacks = list(callbacks)
        if ao_baker is None and config.bake_ao:
            from core.ao import GaussianAOBaker

            ao_baker = GaussianAOBaker()
        self.ao_baker = ao_baker if config.bake_ao else None
        self.extent = scene_extent([v.camera for v in self.views])
        self.generator = torch.Generator().manual_seed(config.seed)
        self.notes: list[str] = []
        self.model = (model.to(self.device) if model is not None else self._initial_model(points))
        self.optimizer = self.model.make_optimizer(config.rates, self.extent)
        self.strategy = DensifyStrategy(config.densify, self.extent)
        self.state = self.strategy.initialize_state(len(self.model), device=self.device)
        self.cameras = [RenderCamera.from_camera(v.camera, device=self.device)
                        for v in self.views]
        self.background = torch.tensor(config.background, dtype=torch.float32,
                                       device=self.device)
        self.ao_targets: list[Tensor] | None = None
        self.ao_seconds: float | None = None
        """Seconds the AO bake took (None until it ran)."""
        self._validated = False
        self.step = 0
        self._order: list[int] = []

    @classmethod
    def from_capture(cls, capture, frame: str, config: TrainConfig = TrainConfig(), *,
                     downscale: float = 1.0, **kwargs) -> Trainer:
        """A trainer on the training cameras (held-out ones excluded) of one frame of a
        `core.data.Capture`, seeded from its points.ply when it has one; `kwargs` go to the
        constructor (model, callbacks, ao_baker)."""
        from core.data.dataset import CaptureDataset
        from core.data.points import read_points_ply

        if frame not in capture.frames:
            raise ValueError(f"frame: {frame!r} is not in {capture.root} (frames "
                             f"{list(capture.frames)[:5]}...)")
        ids = [c.id for c in training_cameras(capture.cameras)]
        if not ids:
            raise ValueError(f"capture: {capture.root} has no training camera (every 8th camera "
                             "is held out, so at least 2 are needed)")
        ds = CaptureDataset(capture, frames=[frame], cameras=ids, downscale=downscale)
        path = capture.points_path()
        if path is not None and config.init.source in ("auto", "points") \
                and kwargs.get("model") is None:
            kwargs["points"] = read_points_ply(path)
        return cls([View.from_sample(ds[i]) for i in range(len(ds))], config, **kwargs)

    def _initial_model(self, points: PointCloud | None) -> GaussianModel:
        seed = seed_points(
            [v.camera for v in self.views], [v.image.cpu().numpy() for v in self.views],
            [None if v.mask is None else v.mask.cpu().numpy() for v in self.views],
            self.config.init, n_random=self.config.init_points, capture_points=points,
            seed=self.config.seed)
        self.notes.append(seed.note)
        return GaussianModel.from_points(seed.points.to(self.device), seed.colors.to(self.device))

    def target(self, index: int, background: Tensor | None = None) -> Tensor:
        """The training image composited on `background` (default the configured one) by its
        mask: mask is coverage, the image straight colour (core.data.dataset)."""
        view = self.views[index]
        if view.mask is None:
            return view.image
        bg = self.background if background is None else background
        return view.image * view.mask + bg * (1 - view.mask)

    def render_view(self, index: int, p: StagePlan, background: Tensor | None = None):
        # The rasterizer reads every value to check it (ms per 100k Gaussians): once per run is
        # enough, since the model's activations keep scales positive and opacities in [0, 1].
        validate, self._validated = not self._validated, True
        return render(self.model, self.cameras[index], sh_degree=p.sh_degree, beta=p.beta,
                      geometry=p.geometry_branch, tie_opacity=p.tie_opacity,
                      background=self.background if background is None else background,
                      eps2d=self.config.eps2d, antialiased=self.config.antialiased,
                      validate=validate)

    def _step_background(self, index: int) -> Tensor:
        if self.config.random_background and self.views[index].mask is not None:
            # Drawn on the CPU generator whatever the device: the same colours everywhere.
            return torch.rand(3, generator=self.generator).to(self.device)
        return self.background

    def _next_view(self) -> int:
        if not self._order:  # every view once per epoch, in random order (3DGS viewpoint stack)
            self._order = torch.randperm(len(self.views), generator=self.generator).tolist()
        return self._order.pop()

    def _losses(self, index: int, p: StagePlan, r, background: Tensor) -> dict[str, Tensor]:
        w, view, cam = self.config.losses, self.views[index], self.cameras[index]
        terms = {"photometric": photometric_loss(r.rgb, self.target(index, background), w)}
        if p.normal_prior and view.normal is not None:
            terms["normal"] = normal_prior_loss(r.normal, view.normal, view.mask, w)
        if p.geometry_branch and not p.tie_opacity and view.mask is not None \
                and w.geometry_mask > 0:
            terms["mask"] = geometry_mask_loss(r.alpha_g, view.mask, w)
        if p.consistency:
            terms["consistency"] = depth_normal_consistency(r.normal, r.depth, r.alpha_g, cam.K,
                                                            cam.viewmat, w)
        if p.visibility and self.ao_targets is not None:
            terms["visibility"] = visibility_loss(r.visibility, self.ao_targets[index], view.mask, w)
        return terms

    def _before_step(self, p: StagePlan) -> None:
        if p.start_geometry:
            from core.render import seen_directions

            centers = torch.stack([c.center for c in self.cameras])
            seen = seen_directions(self.model, self.cameras, eps2d=self.config.eps2d,
                                   antialiased=self.config.antialiased)
            self.model.init_geometry(centers, self.optimizer, seen)
        if p.bake_ao:
            if self.ao_baker is None:
                self.notes.append(f"step {p.step}: AO baking skipped (bake_ao is off); "
                                  "visibility loss off")
            else:
                start = time.perf_counter()
                targets = self.ao_baker(self.model, self.cameras, self.optimizer, p.beta)
                self.ao_targets = to_device(list(targets), self.device)  # a baker's own device
                self.ao_seconds = time.perf_counter() - start
        lr = means_lr(self.config.rates, self.extent, p.step)
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = lr

    def train_step(self) -> StepInfo:
        """One optimisation step at `self.step`, then densification / reset as planned."""
        start = time.perf_counter()
        p = plan(self.step, self.config.schedule)
        self._before_step(p)
        index = self._next_view()
        bg = self._step_background(index)
        r = self.render_view(index, p, bg)
        terms = self._losses(index, p, r, bg)
        total = sum(terms.values())
        total.backward()
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        cam = self.cameras[index]
        self.strategy.update(self.state, r.raster, cam.width, cam.height)
        if p.densify:
            self.strategy.densify(self.model, self.optimizer, self.state, self.generator)
        if p.reset_opacity:
            self.strategy.prune_and_reset(self.model, self.optimizer, self.state, p.tie_opacity)
        losses = {k: float(v.detach()) for k, v in terms.items()}
        losses["total"] = float(total.detach())
        # The render in front of the configured background: rgb = blend + (1 - alpha_c) bg.
        on_config = r.rgb.detach() + (1 - r.alpha_c.detach()) * (self.background - bg)
        info = StepInfo(self.step, p, losses, len(self.model), time.perf_counter() - start,
                        psnr(on_config, self.target(index)))
        self.step += 1
        return info

    def train(self) -> GaussianModel:
        """Run the remaining steps of the schedule; returns the model."""
        for cb in self.callbacks:
            cb.on_train_start(self)
        while self.step < self.config.schedule.iterations:
            info = self.train_step()
            for cb in self.callbacks:
                cb.on_step_end(self, info)
        for cb in self.callbacks:
            cb.on_train_end(self)
        return self.model

    @torch.no_grad()
    def evaluate(self, indices: Sequence[int] | None = None) -> float:
        """Mean PSNR over views (all training views by default) with the current step's plan."""
        p = plan(min(self.step, self.config.schedule.iterations - 1), self.config.schedule)
        ids = range(len(self.views)) if indices is None else indices
        return sum(psnr(self.render_view(i, p).rgb, self.target(i)) for i in ids) / len(ids)

    def save_checkpoint(self, path: str | os.PathLike[str], extra: object = None) -> None:
        """Everything that decides the remaining steps, written atomically: parameters, optimizer
        and strategy state, the step, the random generator (view order, split samples) and the
        views still pending in this epoch, the baked AO targets (so a resumed stage 3 keeps its
        visibility loss); and `extra` (plain data). Resuming from it repeats the uninterrupted
        run exactly (bit for bit on CPU with the same thread count). Every tensor is written
        on the CPU, so the file resumes on any device."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        blob = to_device({
            "step": self.step, "params": {k: v.detach() for k, v in self.model.params.items()},
            "optimizer": self.optimizer.state_dict(), "strategy": asdict(self.state),
            "generator": self.generator.get_state(), "order": list(self._order),
            "ao_targets": self.ao_targets, "ao_seconds": self.ao_seconds,
            "notes": list(self.notes), "extra": extra}, "cpu")
        tmp = path.with_name(path.name + ".tmp")
        torch.save(blob, tmp)
        os.replace(tmp, path)

    def load_checkpoint(self, path: str | os.PathLike[str]) -> object:
        """Resume from `save_checkpoint`'s file (same views and config, any device); returns
        its `extra`."""
        blob = torch.load(path, map_location="cpu", weights_only=True)
        self.model = GaussianModel(blob["params"]).to(self.device)
        self.optimizer = self.model.make_optimizer(self.config.rates, self.extent)
        self.optimizer.load_state_dict(blob["optimizer"])  # moves the moments to the params
        self.state = StrategyState(**to_device(blob["strategy"], self.device))
        self.step = int(blob["step"])
        if "generator" in blob:  # absent from checkpoints written before resume was exact
            self.generator.set_state(blob["generator"])
            self._order = [int(i) for i in blob["order"]]
        self.ao_targets = to_device(blob.get("ao_targets"), self.device)
        self.ao_seconds = blob.get("ao_seconds")
        self.notes = list(blob.get("notes") or [])
        return blob.get("extra")
