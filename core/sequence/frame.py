"""`FrameTracker`: one frame after a GoP's key frame, deformed from the previous frame's Gaussians
and then refined. It runs like `core.train.Trainer` for the pipeline's callbacks (progress,
history, checkpoints): `step`, `iterations`, `model`, `train()`, `save_checkpoint` /
`load_checkpoint` with exact resume.

Steps [0, D) are the deform stage (graph node parameters only; each step averages the losses of
`deform_views` training views and adds a silhouette term; D grows by a round when a retry starts),
[D, D + R) the refine stage (every attribute, temporal L1 to the deformed values, anisotropy,
densification and pruning with track ids). Both render with the key frame's last-step plan (full
SH degree, final beta, geometry branch on).
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import asdict, replace
from pathlib import Path

import torch
from torch import Tensor

from core.device import resolve_device, to_device
from core.losses import (
    coverage_l1,
    depth_normal_consistency,
    normal_prior_loss,
    photometric_loss,
    visibility_loss,
)
from core.model import GaussianModel
from core.render import RenderCamera, render
from core.seeding import scene_extent
from core.sequence.budget import refine_steps
from core.sequence.config import SequenceConfig
from core.sequence.deform import DeformedGaussians, blur, blur_sigma, deform_losses
from core.sequence.graph import build_graph
from core.sequence.rounds import DeformRounds
from core.sequence.starts import StartRace, candidate_starts, race_starts, view_order
from core.sequence.refine import (
    TemporalWeights,
    TrackedState,
    anchors_of,
    anisotropy_loss,
    prune_transparent,
    relabel,
    temporal_loss,
)
from core.stages import plan
from core.strategy import DensifyStrategy
from core.train import Callback, StepInfo, TrainConfig, View, psnr

__all__ = ["FrameTracker"]


class FrameTracker:
    """Deform + refine one frame from `previous` (the last frame's model, its track ids (N,) and
    the group's next unused id); `earlier` (positions (N, 3) and known (N,) of `previous`'s
    Gaussians one frame before, `core.sequence.motion.align_tracks`) starts the deformation from
    the continued motion, and `earliest` (the same, two frames before) from its second-order
    prediction. Runs on `config.device` like `core.train.Trainer` (the inputs are moved
    there; the random generator stays on the CPU)."""

    def __init__(self, views: Sequence[View], previous: GaussianModel, ids: Tensor, next_id: int,
                 config: TrainConfig, sequence: SequenceConfig = SequenceConfig(), *,
                 callbacks: Sequence[Callback] = (), ao_baker=None,
                 reference_loss: float | None = None,
                 earlier: tuple[Tensor, Tensor] | None = None, refine_credit: int = 0,
                 refine_reference: float | None = None,
                 earliest: tuple[Tensor, Tensor] | None = None):
        if not views:
            raise ValueError("views: expected at least one training view")
        if tuple(ids.shape) != (len(previous),):
            raise ValueError(f"ids: expected ({len(previous)},) track ids, got {tuple(ids.shape)}")
        self.device = resolve_device(config.device, "config.device")
        self._validated = False  # before the start race renders
        self.views = [v.to(self.device) for v in views]
        self.config, self.seq = config, sequence
        self.callbacks = list(callbacks)
        previous, ids = previous.to(self.device), ids.long().to(self.device)
        earlier, earliest = to_device((earlier, earliest), self.device)
        self.previous, self.prev_ids, self.next_id = previous, ids, int(next_id)
        self.round_steps, self.nominal_refine = sequence.steps(config.schedule.iterations)
        self.refine_steps = self.nominal_refine
        """Refine-stage steps: the nominal until the refine stage starts, then
        `_refine_budget()` (`SequenceConfig.refine_adapt`)."""
        self.refine_reference = refine_reference
        """End loss the refine budget compares with where there is no `reference_loss` (a
        group's second frame: the median of the run's earlier tracked frames'; None: ask
        `refine_second`)."""
        self.refine_credit = int(refine_credit)
        """Refine steps this frame may run beyond the nominal (negative: a debt it must start
        paying back), `core.sequence.budget.refine_credit`."""
        self.plan = plan(config.schedule.iterations - 1, config.schedule)
        if ao_baker is None and sequence.bake_ao and config.bake_ao:
            from core.ao import GaussianAOBaker

            ao_baker = GaussianAOBaker()
        self.ao_baker = ao_baker if (sequence.bake_ao and config.bake_ao) else None
        self.cameras = [RenderCamera.from_camera(v.camera, device=self.device)
                        for v in self.views]
        self.extent = scene_extent([v.camera for v in self.views])
        self.background = torch.tensor(config.background, dtype=torch.float32,
                                       device=self.device)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.graph = build_graph(previous.means.detach(), sequence.nodes(len(previous)),
                                 node_neighbors=sequence.node_neighbors)
        starts, self.race = self._race_starts(earlier, earliest)
        """The race that ordered the starts: scores, views and renders per start."""
        self.rounds = DeformRounds(starts, self.race.scores, self.round_steps,
                                   order=self.race.order,
                                   reference_loss=reference_loss,
                                   retries=sequence.deform_retries,
                                   ratio=sequence.retry_loss_ratio)
        """The deform rounds: starts, end losses, retries, the kept round (`reference_loss`:
        the previous frame's `deform_loss`, None for no retries)."""
        q, t = self.rounds.first()
        self.node_q, self.node_t = torch.nn.Parameter(q), torch.nn.Parameter(t)
        self.optimizer: torch.optim.Optimizer = torch.optim.Adam(
            [{"params": [self.node_q], "lr": sequence.lr_rotation, "name": "node_q"},
             {"params": [self.node_t], "lr": sequence.lr_translation * self.extent,
              "name": "node_t"}], lr=0.0)
        self.model: GaussianModel = previous
        self.state: TrackedState | None = None
        self.strategy: DensifyStrategy | None = None
        self.ao_targets: list[Tensor] | None = None
        self.notes: list[str] = []
        self.step = 0
        self._order: list[int] = []

    # -- shared pieces -----------------------------------------------------------------------
    def target(self, index: int, background: Tensor | None = None) -> Tensor:
        view = self.views[index]
        if view.mask is None:
            return view.image
        bg = self.background if background is None else background
        return view.image * view.mask + bg * (1 - view.mask)

    def _next_view(self) -> int:
        if not self._order:
            self._order = torch.randperm(len(self.views), generator=self.generator).tolist()
        return self._order.pop()

    def _background(self, index: int) -> Tensor:
        if self.config.random_background and self.views[index].mask is not None:
            return torch.rand(3, generator=self.generator).to(self.device)  # CPU draws
        return self.background

    def _render(self, model, index: int, background: Tensor):
        p = self.plan
        # Values checked once per frame, as core.train.Trainer does.
        validate, self._validated = not self._validated, True
        return render(model, self.cameras[index], sh_degree=p.sh_degree, beta=p.beta,
                      geometry=True, tie_opacity=False, background=background,
                      eps2d=self.config.eps2d, antialiased=self.config.antialiased,
                      validate=validate)

    def _photometric(self, r, index: int, background: Tensor, sigma: float) -> Tensor:
        return photometric_loss(blur(r.rgb, sigma), blur(self.target(index, background), sigma),
                                self.config.losses)

    def _silhouette(self, r, index: int, sigma: float) -> Tensor | None:
        """`deform_mask` x mean |blur(alpha_c) - blur(mask)|; None without a mask (or weight)."""
        mask = self.views[index].mask
        if self.seq.deform_mask <= 0 or mask is None:
            return None
        return self.seq.deform_mask * coverage_l1(blur(r.alpha_c, sigma), blur(mask, sigma))

    def _image_terms(self, r, index: int, background: Tensor, sigma: float = 0.0) -> dict:
        w, view, cam = self.config.losses, self.views[index], self.cameras[index]
        terms = {"photometric": self._photometric(r, index, background, sigma)}
        if view.normal is not None:
            terms["normal"] = normal_prior_loss(r.normal, view.normal, view.mask, w)
        terms["consistency"] = depth_normal_consistency(r.normal, r.depth, r.alpha_g, cam.K,
                                                        cam.viewmat, w)
        return terms

    def _race_starts(self, earlier, earliest) -> tuple[dict, StartRace]:
        """The candidate starts (`core.sequence.starts.candidate_starts`) and the race that
        ordered them (`SequenceConfig.start_views`, `start_race`)."""
        s = self.seq
        starts = candidate_starts(self.graph, self.previous.means.detach(), earlier, earliest,
                                  s.motion_candidates, s.second_order)
        posed: dict[str, DeformedGaussians] = {}

        def loss(name: str, index: int) -> float:
            if name not in posed:
                posed[name] = DeformedGaussians(self.previous, self.graph, *starts[name])
            return self._start_loss(posed[name], index)

        centres = torch.stack([c.center for c in self.cameras])
        race = race_starts(list(starts), loss, view_order(centres.cpu()), s.start_views,
                           s.start_race)
        return starts, race

    @torch.no_grad()
    def _start_loss(self, posed: DeformedGaussians, index: int) -> float:
        """The image loss (photometric + silhouette) a round's first step would see on view
        `index` from the posed start, at its blur."""
        sigma = self.seq.coarse_sigma
        r = self._render(posed, index, self.background)
        silhouette = self._silhouette(r, index, sigma)
        return float(self._photometric(r, index, self.background, sigma)) + (
            0.0 if silhouette is None else float(silhouette))

    # -- stages ------------------------------------------------------------------------------
    def _deform_step(self, index: int, bg: Tensor) -> tuple[dict, object]:
        s = self.seq
        k = self.step - self.round_start  # step within this round
        decay = 0.1 ** (k / self.round_steps)  # exponential, to a tenth by the round's end
        for group, base in zip(self.optimizer.param_groups,
                               (s.lr_rotation, s.lr_translation * self.extent)):
            group["lr"] = base * decay
        posed = DeformedGaussians(self.previous, self.graph, self.node_q, self.node_t)
        sigma = blur_sigma(k, self.round_steps, s.coarse_sigma)
        views = [(index, bg)] + [(i, self._background(i)) for i in
                                 (self._next_view() for _ in range(s.deform_views - 1))]
        terms: dict[str, Tensor] = {}
        first = None  # the step's own view (index), which StepInfo's PSNR compares
        for i, b in views:
            r = self._render(posed, i, b)
            if first is None:
                first = r
            view_terms = self._image_terms(r, i, b, sigma)
            silhouette = self._silhouette(r, i, sigma)
            if silhouette is not None:
                view_terms["silhouette"] = silhouette
            for name, value in view_terms.items():
                terms[name] = terms.get(name, 0.0) + value / len(views)
        self.rounds.record(float(terms["photometric"].detach())
                           + float(terms.get("silhouette", torch.zeros(())).detach()))
        terms.update(deform_losses(self.graph, self.node_q, self.node_t, arap=s.arap,
                                   quat_norm=s.quat_norm))
        return terms, first

    def _refine_budget(self) -> int:
        """Refine steps for how the deform stage ended (`core.sequence.budget.refine_steps`;
        a group's second frame compares with `refine_reference`)."""
        return refine_steps(self.seq, self.nominal_refine, self.rounds.deform_loss,
                            self.rounds.reference_loss or self.refine_reference,
                            self.refine_credit, self.scoring_extra)

    def _start_refine(self) -> None:
        """The deformed Gaussians become the model; anchors, ids, optimizer, strategy start."""
        s, cfg = self.seq, self.config
        self.refine_steps = self._refine_budget()
        with torch.no_grad():
            self.model = DeformedGaussians(self.previous, self.graph, self.node_q,
                                           self.node_t).to_model()
        self.optimizer = self.model.make_optimizer(cfg.rates, self.extent)
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = cfg.rates.means * self.extent * s.means_lr_scale
        cap = int(len(self.model) * (1 + s.max_growth))
        if cfg.densify.max_gaussians is not None:
            cap = min(cap, max(cfg.densify.max_gaussians, len(self.model)))
        self.strategy = DensifyStrategy(replace(cfg.densify, max_gaussians=cap), self.extent)
        z = torch.zeros(len(self.model), device=self.device)
        # resets=1: the key frame's resets are behind it, so too-big Gaussians are pruned.
        self.state = TrackedState(z.clone(), z.clone(), z.clone(), z.clone(), z.clone(),
                                  rho=cfg.densify.rho, resets=1, ids=self.prev_ids.clone(),
                                  anchor=anchors_of(self.model), next_id=self.next_id)
        if self.ao_baker is not None:
            self.ao_targets = to_device(list(self.ao_baker(self.model, self.cameras,
                                                           self.optimizer, self.plan.beta)),
                                        self.device)

    def _refine_step(self, index: int, bg: Tensor) -> tuple[dict, object]:
        s, view = self.seq, self.views[index]
        r = self._render(self.model, index, bg)
        terms = self._image_terms(r, index, bg)
        if self.ao_targets is not None:
            terms["visibility"] = visibility_loss(r.visibility, self.ao_targets[index], view.mask,
                                                  self.config.losses)
        if s.temporal:
            weights = TemporalWeights(s.temporal_opacity_g, s.temporal_means, s.temporal_quats,
                                      s.temporal_normals)
            terms.update(temporal_loss(self.model, self.state.anchor, weights))
        if s.anisotropy > 0:
            terms["anisotropy"] = anisotropy_loss(self.model.scales, s.anisotropy,
                                                  s.anisotropy_ratio)
        return terms, r

    def _after_refine_step(self, r, index: int) -> None:
        cam = self.cameras[index]
        self.strategy.update(self.state, r.raster, cam.width, cam.height)
        k = self.step - self.deform_steps + 1  # refine steps done
        every = self.seq.densify_every or max(1, self.refine_steps // 4)
        if k % every == 0 and k < self.refine_steps:
            self.strategy.densify(self.model, self.optimizer, self.state, self.generator)
            relabel(self.state, self.model)
            prune_transparent(self.model, self.optimizer, self.state,
                              self.config.densify.transparent)

    def _end_round(self) -> None:
        """A deform round ended: start another (fresh rates, blur and Adam moments) or keep the
        best round's node parameters (`DeformRounds.end`)."""
        end = self.rounds.end(self.node_q, self.node_t)
        start = end.start if end.retry else (end.q, end.t)
        if start is not None:
            with torch.no_grad():
                self.node_q.copy_(start[0])
                self.node_t.copy_(start[1])
        if end.retry:
            self.optimizer.state.clear()
            self.notes.append(end.note)

    def train_step(self) -> StepInfo:
        start = time.perf_counter()
        if self.step == self.deform_steps and self.state is None and self.rounds.kept is None:
            self._end_round()
        if self.step == self.deform_steps and self.state is None:
            self._start_refine()
        index = self._next_view()
        bg = self._background(index)
        deforming = self.step < self.deform_steps
        terms, r = (self._deform_step if deforming else self._refine_step)(index, bg)
        total = sum(terms.values())
        total.backward()
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        if not deforming:
            self._after_refine_step(r, index)
        losses = {k: float(v.detach()) for k, v in terms.items()}
        losses["total"] = float(total.detach())
        on_config = r.rgb.detach() + (1 - r.alpha_c.detach()) * (self.background - bg)
        info = StepInfo(self.step, self.plan, losses, len(self.model),
                        time.perf_counter() - start, psnr(on_config, self.target(index)))
        self.step += 1
        return info

    def train(self) -> GaussianModel:
        for cb in self.callbacks:
            cb.on_train_start(self)
        while self.step < self.iterations:
            if self.step == self.deform_steps and self.state is None and self.rounds.kept is None:
                self._end_round()  # before the refine stage: a lost track stops here
                continue
            if self.lost_track is not None:
                break
            info = self.train_step()
            for cb in self.callbacks:
                cb.on_step_end(self, info)
        for cb in self.callbacks:
            cb.on_train_end(self)
        return self.model

    @property
    def lost_track(self) -> float | None:
        """Once the deform stage is over: the kept round's end-loss ratio to the previous frame's
        when it reaches `rekey_loss_ratio` (the frame is to be made a key frame instead; `train`
        stops before the refine stage), else None."""
        limit, ref, end = self.seq.rekey_loss_ratio, self.rounds.reference_loss, self.deform_loss
        if limit <= 0 or not ref or end is None or end < limit * ref:
            return None
        return end / ref

    @property
    def renders_done(self) -> int:
        """`renders` of the steps run so far (a frame stopped by `lost_track` paid these)."""
        deform = min(self.step, self.deform_steps)
        return (deform * self.seq.deform_views + max(0, self.step - self.deform_steps)
                + self._scoring_renders())

    def _scoring_renders(self) -> int:
        return (self.race.renders + 1) // 2

    @property
    def scoring_extra(self) -> int:
        """Scoring renders (as `renders` counts them) the start race took beyond scoring every
        start on `start_views` views; the refine stage pays them back
        (`_refine_budget`), so a close race costs the run no more renders."""
        starts = len(self.race.views)
        base = starts * min(self.seq.start_views, len(self.views)) if starts > 1 else 0
        return max(0, self._scoring_renders() - (base + 1) // 2)

    @property
    def retries(self) -> int:
        """Deform rounds added (`deform_retries`)."""
        return self.rounds.retries

    @property
    def deform_loss(self) -> float | None:
        """End loss of the kept deform round (the next frame's reference for retries)."""
        return self.rounds.deform_loss

    @property
    def start(self) -> str:
        """Name of the start the kept deform round began from ("rest", "damped a",
        "second-order c": `_candidate_starts`)."""
        return self.rounds.start

    @property
    def deform_steps(self) -> int:
        """Steps of the deform stage: one round, plus one per retry."""
        return self.round_steps * (1 + self.retries)

    @property
    def round_start(self) -> int:
        """First step of the current deform round (its rates and blur count from there)."""
        return self.round_steps * self.retries

    @property
    def iterations(self) -> int:
        """Steps of the frame (grows by a deform round when a retry starts)."""
        return self.deform_steps + self.refine_steps

    @property
    def renders(self) -> int:
        """Images rendered and back-propagated in all: the frame's cost in key-frame steps. The
        start's scoring renders (forward only: the rasterizer's forward is about 40% of a
        training render's time) count half each, rounded up."""
        return (self.deform_steps * self.seq.deform_views + self.refine_steps
                + self._scoring_renders())

    @property
    def phase(self) -> str:
        """'deform' or 'refine': the stage of the next step."""
        return "deform" if self.step < self.deform_steps else "refine"

    @property
    def ids(self) -> Tensor:
        """(N,) track ids of the current model's Gaussians."""
        return self.prev_ids if self.state is None else self.state.ids

    @property
    def group_next_id(self) -> int:
        return self.next_id if self.state is None else self.state.next_id

    @torch.no_grad()
    def evaluate(self) -> float:
        """Mean PSNR over the training views."""
        model = self.model if self.state is not None else DeformedGaussians(
            self.previous, self.graph, self.node_q, self.node_t)
        return sum(psnr(self._render(model, i, self.background).rgb, self.target(i))
                   for i in range(len(self.views))) / len(self.views)

    # -- checkpoints -------------------------------------------------------------------------
    def save_checkpoint(self, path: str | os.PathLike[str], extra: object = None) -> None:
        """Everything the remaining steps depend on, written atomically with every tensor on the
        CPU (the graph is rebuilt from the previous frame, deterministically)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        blob = {"step": self.step, "rounds": self.rounds.state_dict(),
                "node_q": self.node_q.detach(), "node_t": self.node_t.detach(),
                "optimizer": self.optimizer.state_dict(), "generator": self.generator.get_state(),
                "order": list(self._order), "notes": list(self.notes), "extra": extra}
        if self.state is not None:
            st = asdict(self.state)
            blob.update(params={k: v.detach() for k, v in self.model.params.items()},
                        state=st, ao_targets=self.ao_targets)
        tmp = path.with_name(path.name + ".tmp")
        torch.save(to_device(blob, "cpu"), tmp)
        os.replace(tmp, path)

    def load_checkpoint(self, path: str | os.PathLike[str]) -> object:
        """Resume from `save_checkpoint`'s file (written on any device); returns its `extra`."""
        blob = torch.load(path, map_location="cpu", weights_only=True)
        with torch.no_grad():
            self.node_q.copy_(blob["node_q"])
            self.node_t.copy_(blob["node_t"])
        self.step = int(blob["step"])
        if "rounds" in blob:
            self.rounds.load_state_dict(to_device(blob["rounds"], self.device))
        else:  # a checkpoint from before the rounds were kept: its retry count only
            self.rounds.retries = int(blob.get("retries", 0))
        if "params" in blob:
            self._start_refine_from(blob)
        self.optimizer.load_state_dict(blob["optimizer"])
        self.generator.set_state(blob["generator"])
        self._order = [int(i) for i in blob["order"]]
        self.notes = list(blob.get("notes") or [])
        return blob.get("extra")

    def _start_refine_from(self, blob: dict) -> None:
        baker, self.ao_baker = self.ao_baker, None  # targets come from the checkpoint
        try:
            self._start_refine()
        finally:
            self.ao_baker = baker
        self.model = GaussianModel(blob["params"]).to(self.device)
        self.optimizer = self.model.make_optimizer(self.config.rates, self.extent)
        self.state = TrackedState(**to_device(blob["state"], self.device))
        self.ao_targets = to_device(blob.get("ao_targets"), self.device)
