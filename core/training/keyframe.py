"""`Trainer`: a key frame reconstructed from scratch with the staged schedule (docs/design.md
section 5.2): random initial points, then per step the stage's losses, densification and
opacity resets; the geometry branch starts at stage 2 and ambient occlusion is baked at
stage 3's first step by a hook (`AOBaker`, by default `core.ao.GaussianAOBaker` on the native
ray tracer; with `bake_ao` off the visibility loss stays off and a note says so)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict
from typing import Protocol

import torch
from torch import Tensor

from core.ao import GaussianAOBaker
from core.config import TrainConfig, Views, select_views
from core.device import to_device
from core.data.points import PointCloud, read_points_ply
from core.losses import sparsity_loss
from core.model import GaussianModel, means_lr
from core.render import RenderCamera, seen_directions
from core.rig.geometry import RigGeometry
from core.seeding import Seed, seed_points
from core.stages import StagePlan, plan
from core.strategy import DensifyStrategy, StrategyState
from core.training.callbacks import Callback
from core.training.loop import FrameFitter
from core.training.terms import image_terms
from core.training.views import View, frame_views

__all__ = ["AOBaker", "Trainer"]


class AOBaker(Protocol):
    """Bakes visibility: per-Gaussian values written into the model (through the optimizer, so
    Adam's moments follow), per-view target maps (H, W, 1) returned."""

    def __call__(self, model: GaussianModel, cameras: Sequence[RenderCamera],
                 optimizer: torch.optim.Optimizer, beta: float) -> list[Tensor]: ...


class Trainer(FrameFitter):
    """Reconstructs one key frame from its training views (module docstring). A `model` given
    to it is trained in place when it is on the trainer's device (densification replaces its
    tensors): give a copy to keep the original (two trainers given one model do not start from
    the same Gaussians)."""

    def __init__(self, views: Sequence[View], config: TrainConfig = TrainConfig(), *,
                 model: GaussianModel | None = None, callbacks: Sequence[Callback] = (),
                 ao_baker: AOBaker | None = None, points: PointCloud | None = None,
                 static: PointCloud | None = None, clear_of: Sequence = ()):
        super().__init__(views, config, callbacks=callbacks)
        self.schedule = config.schedule.for_views(len(self.views))
        """The schedule these views follow (`Schedule.for_views`)."""
        if ao_baker is None and config.bake_ao:
            ao_baker = GaussianAOBaker(config.ao)
        self.ao_baker = ao_baker if config.bake_ao else None
        self.rig = RigGeometry([v.camera for v in self.views],
                               [v.image.cpu().numpy() for v in self.views],
                               [None if v.mask is None else v.mask.cpu().numpy()
                                for v in self.views], config.init.stereo,
                               threads=torch.get_num_threads())
        """The views' sparse points, fused depth and normal priors, each made on first use."""
        self.seed: Seed | None = None
        """The seeds it started from (None: given a model)."""
        self.seed_seconds: float | None = None
        self.model = (model.to(self.device) if model is not None
                      else self._initial_model(points, static, clear_of))
        self.optimizer = self.model.make_optimizer(config.rates, self.extent)
        self.strategy = DensifyStrategy(config.densify, self.extent)
        self.state = self.strategy.initialize_state(len(self.model), device=self.device)

    @classmethod
    def from_capture(cls, capture, frame: str, config: TrainConfig = TrainConfig(), *,
                     views: Views | None = None, **kwargs) -> Trainer:
        """A trainer on the training views of one frame of a `core.data.Capture` as the run's
        `views` select them (None: the capture's defaults with `config.masks`), seeded from
        its points.ply when it has one; `kwargs` go to the constructor (model, callbacks,
        ao_baker, static)."""
        path = capture.points_path()
        if path is not None and config.init.source in ("auto", "points") \
                and kwargs.get("model") is None:
            kwargs["points"] = read_points_ply(path)
        selected = views or select_views(capture, masks=config.masks)
        kwargs.setdefault("clear_of", capture.cameras)  # held-out cameras' lenses too
        return cls(frame_views(capture, frame, selected), config, **kwargs)

    def _initial_model(self, points: PointCloud | None, static: PointCloud | None,
                       clear_of: Sequence) -> GaussianModel:
        start = time.perf_counter()
        subjects = [None if v.subject is None else v.subject.cpu().numpy() for v in self.views]
        seed = seed_points(
            self.rig.cameras, self.rig.images, self.rig.masks, self.config.init,
            n_random=self.config.init_points, capture_points=points, seed=self.config.seed,
            rig=self.rig, max_gaussians=self.config.densify.max_gaussians,
            subjects=subjects if any(m is not None for m in subjects) else None, static=static,
            threads=torch.get_num_threads(), clear_of=clear_of)
        self.seed, self.seed_seconds = seed, time.perf_counter() - start
        self.notes.append(seed.note)
        return GaussianModel.from_points(seed.points.to(self.device),
                                         seed.colors.to(self.device))

    @property
    def iterations(self) -> int:
        return self.config.schedule.iterations

    @property
    def renders(self) -> int:
        """Images rendered and back-propagated: one a step."""
        return self.iterations

    def current(self) -> tuple[GaussianModel, StagePlan]:
        return self.model, self.plan_at(min(self.step, self.iterations - 1))

    def plan_at(self, step: int) -> StagePlan:
        """The stage plan of `step` for the configured method (the schedule for these views:
        `Schedule.for_views`)."""
        return plan(step, self.schedule, self.config.method)

    def before_step(self) -> None:
        p = self.plan_at(self.step)
        if p.start_geometry:
            self._start_geometry()
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

    def step_terms(self, index: int, background: Tensor) -> tuple[dict, object, StagePlan]:
        p = self.plan_at(self.step)
        r = self.render_view(self.model, index, p, background)
        terms = image_terms(r, self.views[index], self.cameras[index],
                            self.target(index, background), p, self.config.losses,
                            ao_target=None if self.ao_targets is None else self.ao_targets[index])
        w = self.config.losses
        if w.opacity_l1 > 0 or w.scale_l1 > 0:
            own_g = p.geometry_branch and not p.tie_opacity
            opacities = [self.model.opacity_c] + ([self.model.opacity_g] if own_g else [])
            terms["sparsity"] = sparsity_loss(opacities, self.model.scales, self.extent, w)
        return terms, r, p

    def train(self) -> GaussianModel:
        """Run the remaining steps; a plain 3DGS then gets the geometry a 3DGS user reads off
        it (normals along each Gaussian's shortest axis, facing the cameras that see it, and
        the geometry opacity equal to its one opacity), so that its renders, meshes and
        relighting show what a 3DGS gives."""
        super().train()
        if self.config.method == "3dgs":
            self._start_geometry()
        return self.model

    def _start_geometry(self) -> None:
        centers = torch.stack([c.center for c in self.cameras])
        seen = seen_directions(self.model, self.cameras, eps2d=self.config.eps2d,
                               antialiased=self.config.antialiased)
        self.model.init_geometry(centers, self.optimizer, seen)

    def after_step(self, r, index: int, p: StagePlan) -> None:
        cam = self.cameras[index]
        self.strategy.update(self.state, r.raster, cam.width, cam.height)
        if p.densify:
            self.strategy.densify(self.model, self.optimizer, self.state, self.generator,
                                  p.tie_opacity)
        if p.reset_opacity:
            self.strategy.prune_and_reset(self.model, self.optimizer, self.state, p.tie_opacity)

    def state_blob(self) -> dict:
        """Parameters, densification statistics and the baked AO targets (so a resumed
        stage 3 keeps its visibility loss)."""
        return {"params": {k: v.detach() for k, v in self.model.params.items()},
                "strategy": asdict(self.state), "ao_targets": self.ao_targets,
                "ao_seconds": self.ao_seconds}

    def load_state_blob(self, blob: dict) -> None:
        self.model = GaussianModel(blob["params"]).to(self.device)
        self.optimizer = self.model.make_optimizer(self.config.rates, self.extent)
        self.state = StrategyState(**to_device(blob["strategy"], self.device))
        self.ao_targets = to_device(blob.get("ao_targets"), self.device)
        self.ao_seconds = blob.get("ao_seconds")
