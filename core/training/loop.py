"""`FrameFitter`: the loop every frame is fitted with, a key frame (`core.training.keyframe.
Trainer`) and a tracked frame (`core.sequence.tracker.FrameTracker`) alike. It owns the views on
the device, their targets and backgrounds, the view order, the step loop with its callbacks, the
running PSNR, and checkpoints with exact resume; a subclass says what is optimised:

- `iterations`: the steps of the frame;
- `before_step()`: what happens at the step boundary (stage changes, bakes, rates);
- `step_terms(index, background)`: the loss terms of one step on one view, with the render and
  the plan it used;
- `after_step(render, index, plan)`: densification and pruning;
- `current()`: the model and plan that render the frame now (for `evaluate`);
- `state_blob()` / `load_state_blob(blob)`: what else a checkpoint holds.

Runs on `config.device`: the model, the optimizer state, the views and the cameras live there;
the random generator stays on the CPU (its draws are moved), so a run draws the same numbers on
any device and its checkpoint resumes anywhere.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence

import torch
from torch import Tensor

from core.config import TrainConfig
from core.data.layout import near_plane
from core.device import resolve_device, to_device
from core.files import atomic_path
from core.metrics import psnr
from core.model import GaussianModel
from core.render import RenderCamera, render
from core.seeding import scene_extent
from core.stages import StagePlan
from core.training.callbacks import Callback, StepInfo
from core.training.views import View

__all__ = ["FrameFitter"]


class FrameFitter:
    """The step loop of one frame (module docstring)."""

    model: GaussianModel
    optimizer: torch.optim.Optimizer
    phase: str = "key"
    """How the frame is made: 'key' (static stages), or a tracked frame's 'deform' / 'refine'
    stage of the next step."""

    def __init__(self, views: Sequence[View], config: TrainConfig, *,
                 callbacks: Sequence[Callback] = ()):
        if not views:
            raise ValueError("views: expected at least one training view")
        self.config = config
        self.device = resolve_device(config.device, "config.device")
        self.views = [v.to(self.device) for v in views]
        self.callbacks = list(callbacks)
        self.extent = scene_extent([v.camera for v in self.views])
        self.generator = torch.Generator().manual_seed(config.seed)
        self.near = config.near if config.near is not None else \
            near_plane([v.camera for v in self.views])
        """The near plane of every render of the frame (`TrainConfig.near`; None, as a config
        not resolved with a run has it: the training cameras' rig's)."""
        self.cameras = [RenderCamera.from_camera(v.camera, device=self.device, near=self.near)
                        for v in self.views]
        self.background = torch.tensor(config.background, dtype=torch.float32,
                                       device=self.device)
        self.ao_targets: list[Tensor] | None = None
        self.ao_seconds: float | None = None
        """Seconds the frame's AO bake took (None: no bake)."""
        self.notes: list[str] = []
        self.step = 0
        self._order: list[int] = []
        self._validated = False

    # -- what a subclass provides ------------------------------------------------------------
    @property
    def iterations(self) -> int:
        raise NotImplementedError

    def before_step(self) -> None:
        """The step boundary before step `self.step`."""

    def step_terms(self, index: int, background: Tensor) -> tuple[dict, object, StagePlan]:
        raise NotImplementedError

    def before_update(self) -> None:
        """Between the backward pass and the optimizer step (gradients may be edited)."""

    def after_step(self, r, index: int, p: StagePlan) -> None:
        """After the optimizer step (densification, pruning)."""

    def current(self) -> tuple[object, StagePlan]:
        raise NotImplementedError

    def state_blob(self) -> dict:
        raise NotImplementedError

    def load_state_blob(self, blob: dict) -> None:
        raise NotImplementedError

    # -- shared pieces -----------------------------------------------------------------------
    def target(self, index: int, background: Tensor | None = None) -> Tensor:
        """The training image composited on `background` (default the configured one) by its
        mask: mask is coverage, the image straight colour (core.data.dataset)."""
        view = self.views[index]
        if view.mask is None:
            return view.image
        bg = self.background if background is None else background
        return view.image * view.mask + bg * (1 - view.mask)

    def render_view(self, model, index: int, p: StagePlan, background: Tensor | None = None):
        """`model` (a GaussianModel or a deformed one) seen by training camera `index`. The
        rasterizer reads every value to check it (ms per 100k Gaussians): the first render of
        a frame is checked, the rest not, since the model's activations keep scales positive
        and opacities in [0, 1]."""
        validate, self._validated = not self._validated, True
        return render(model, self.cameras[index], sh_degree=p.sh_degree, beta=p.beta,
                      geometry=p.geometry_branch, tie_opacity=p.tie_opacity,
                      background=self.background if background is None else background,
                      eps2d=self.config.eps2d, antialiased=self.config.antialiased,
                      validate=validate)

    def next_view(self) -> int:
        """Every view once per epoch, in random order (3DGS viewpoint stack)."""
        if not self._order:
            self._order = torch.randperm(len(self.views), generator=self.generator).tolist()
        return self._order.pop()

    def step_background(self, index: int) -> Tensor:
        """A new random colour for a masked view (drawn on the CPU generator whatever the
        device: the same colours everywhere), else the configured background."""
        if self.config.random_background and self.views[index].mask is not None:
            # non_blocking: a small pageable copy that need not wait for the queued steps.
            return torch.rand(3, generator=self.generator).to(self.device, non_blocking=True)
        return self.background

    # -- the loop ----------------------------------------------------------------------------
    def train_step(self) -> StepInfo:
        """One optimisation step at `self.step`."""
        start = time.perf_counter()
        self.before_step()
        index = self.next_view()
        bg = self.step_background(index)
        terms, r, p = self.step_terms(index, bg)
        total = sum(terms.values())
        total.backward()
        self.before_update()
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.after_step(r, index, p)
        values = {k: v.detach() for k, v in terms.items()}
        values["total"] = total.detach()
        # The render in front of the configured background: rgb = blend + (1 - alpha_c) bg.
        on_config = r.rgb.detach() + (1 - r.alpha_c.detach()) * (self.background - bg)
        mse = (on_config - self.target(index)).square().mean()
        info = StepInfo(self.step, p, values, len(self.model), time.perf_counter() - start, mse)
        self.step += 1
        return info

    def train(self) -> GaussianModel:
        """Run the remaining steps; returns the model."""
        for cb in self.callbacks:
            cb.on_train_start(self)
        while self.step < self.iterations:
            info = self.train_step()
            for cb in self.callbacks:
                cb.on_step_end(self, info)
        for cb in self.callbacks:
            cb.on_train_end(self)
        return self.model

    @torch.no_grad()
    def evaluate(self, indices: Sequence[int] | None = None) -> float:
        """Mean PSNR over views (all training views by default) as the frame renders now."""
        model, p = self.current()
        ids = range(len(self.views)) if indices is None else indices
        return sum(psnr(self.render_view(model, i, p).rgb, self.target(i))
                   for i in ids) / len(ids)

    # -- checkpoints -------------------------------------------------------------------------
    def save_checkpoint(self, path: str | os.PathLike[str], extra: object = None) -> None:
        """Everything the remaining steps depend on, written atomically: the subclass's state,
        the optimizer, the step, the random generator and the views still pending in this
        epoch, notes, and `extra` (plain data). Resuming repeats the uninterrupted run exactly
        (bit for bit on the CPU with the same thread count). Every tensor is written on the
        CPU, so the file resumes on any device."""
        blob = {**self.state_blob(), "step": self.step,
                "optimizer": self.optimizer.state_dict(), "generator": self.generator.get_state(),
                "order": list(self._order), "notes": list(self.notes), "extra": extra}
        with atomic_path(path) as tmp:
            torch.save(to_device(blob, "cpu"), tmp)

    def load_checkpoint(self, path: str | os.PathLike[str]) -> object:
        """Resume from `save_checkpoint`'s file (same views and config, any device); returns
        its `extra`."""
        blob = torch.load(path, map_location="cpu", weights_only=True)
        self.step = int(blob["step"])
        self.load_state_blob(blob)
        self.optimizer.load_state_dict(blob["optimizer"])  # moves the moments to the params
        self.generator.set_state(blob["generator"])
        self._order = [int(i) for i in blob["order"]]
        self.notes = list(blob.get("notes") or [])
        return blob.get("extra")
