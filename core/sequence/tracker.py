"""`FrameTracker`: a frame after its group's key frame, fitted on the shared loop
(`core.training.FrameFitter`) by deforming the previous frame's Gaussians and then refining
them (docs/design.md section 5.9).

Steps [0, D) are the deform stage: the graph's node rotations and translations only, from the
start the race chose (`core.sequence.starts`); each step averages the losses of `deform_views`
training views, blurred at first, and adds a silhouette term. Its end loss (the mean image loss
of its last sixth of steps) is the frame's `deform_loss`, which sets the refine budget
(`core.sequence.budget`). Steps [D, D + R) are the refine stage: every attribute, temporal L1 to
the deformed values, anisotropy, densification and pruning that keep track ids. Both stages
render with the key frame's last-step plan (full SH degree, final beta, geometry branch on).

With `moving` (a scene whose subject masks say what moves, `SequenceConfig.moving`) only those
Gaussians take part: the graph is built on them, the refine stage updates, densifies and prunes
only them, and the rest of the scene stays bit for bit as the previous frame had it.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, replace

import torch
from torch import Tensor

from core.ao import GaussianAOBaker
from core.config import SequenceConfig, TrainConfig
from core.device import to_device
from core.losses import blur, coverage_l1, photometric_loss
from core.model import GaussianModel
from core.sequence.budget import refine_steps
from core.sequence.deform import DeformedGaussians, blur_sigma, deform_losses
from core.sequence.graph import build_graph
from core.sequence.refine import (
    TemporalWeights,
    TrackedState,
    anchors_of,
    anisotropy_loss,
    prune_transparent,
    relabel,
    temporal_loss,
)
from core.sequence.starts import StartRace, candidate_starts, race_starts, view_order
from core.stages import StagePlan, plan
from core.strategy import DensifyStrategy
from core.training import Callback, FrameFitter, View
from core.training.terms import image_terms

__all__ = ["FrameTracker"]


class FrameTracker(FrameFitter):
    """Deform + refine one frame from `previous` (the last frame's model, its track ids (N,)
    and the group's next unused id). `earlier` (positions (N, 3) and known (N,) of
    `previous`'s Gaussians one frame before, `core.sequence.motion.align_tracks`) adds starts
    that continue the motion, `earliest` (two frames before) second-order ones.
    `reference_loss` is the previous frame's deform loss (None after a key frame, which then
    compares with `refine_reference`); `refine_credit` the refine steps it may run beyond the
    nominal (negative: a debt to pay back), `core.sequence.budget.refine_credit`."""

    def __init__(self, views: Sequence[View], previous: GaussianModel, ids: Tensor,
                 next_id: int, config: TrainConfig, sequence: SequenceConfig = SequenceConfig(),
                 *, callbacks: Sequence[Callback] = (), ao_baker=None,
                 reference_loss: float | None = None,
                 earlier: tuple[Tensor, Tensor] | None = None, refine_credit: int = 0,
                 refine_reference: float | None = None,
                 earliest: tuple[Tensor, Tensor] | None = None, moving: Tensor | None = None):
        if tuple(ids.shape) != (len(previous),):
            raise ValueError(f"ids: expected ({len(previous)},) track ids, got {tuple(ids.shape)}")
        if moving is not None and tuple(moving.shape) != (len(previous),):
            raise ValueError(f"moving: expected ({len(previous)},) bool, got "
                             f"{tuple(moving.shape)}")
        super().__init__(views, config, callbacks=callbacks)
        self.seq = sequence
        previous, ids = previous.to(self.device), ids.long().to(self.device)
        earlier, earliest = to_device((earlier, earliest), self.device)
        self.previous, self.prev_ids, self.next_id = previous, ids, int(next_id)
        self.deform_steps, self.nominal_refine = sequence.steps(config.schedule.iterations)
        self.refine_steps = self.nominal_refine
        """The nominal until the refine stage starts, then `_refine_budget()`."""
        self.reference_loss, self.refine_reference = reference_loss, refine_reference
        self.refine_credit = int(refine_credit)
        # The key frame's last-step plan; the method's geometry branch on whatever the schedule.
        self.plan = plan(config.schedule.iterations - 1, config.schedule, config.method)
        if config.method == "disentangled":
            self.plan = replace(self.plan, geometry_branch=True, tie_opacity=False)
        if ao_baker is None and sequence.bake_ao and config.bake_ao:
            ao_baker = GaussianAOBaker(config.ao)
        self.ao_baker = ao_baker if sequence.bake_ao and config.bake_ao else None
        self.moving = None if moving is None or bool(moving.all()) else moving.to(self.device)
        """(N,) bool: the Gaussians this frame moves (None: all)."""
        if self.moving is not None and int(self.moving.sum()) < 5:
            self.moving = None  # no subject to speak of: move everything
            self.notes.append("fewer than 5 Gaussians inside the subject hull: all move")
        self.rows = None if self.moving is None else self.moving.nonzero()[:, 0]
        """Indices of the moving Gaussians in `previous` (None: all)."""
        moved = previous.means.detach() if self.rows is None else \
            previous.means.detach()[self.rows]
        self.graph = build_graph(moved, sequence.nodes(len(moved)),
                                 node_neighbors=sequence.node_neighbors)
        self.starts, self.race = self._race_starts(earlier, earliest)
        """The candidate starts' node parameters by name, and the race that ordered them
        (scores, views and renders per start)."""
        self.start: str = self.race.order[0]
        """The start the deform stage began from ("rest", "damped a", "second-order c")."""
        self.deform_losses: list[float] = []
        """Image loss of each deform step (`_read_losses` brings the pending ones over)."""
        self._pending_losses: list[Tensor] = []
        self.deform_loss: float | None = None
        """End loss of the deform stage (the next frame's reference), once it is over."""
        q, t = self.starts[self.start]
        self.node_q, self.node_t = torch.nn.Parameter(q), torch.nn.Parameter(t)
        self.optimizer = torch.optim.Adam(
            [{"params": [self.node_q], "lr": sequence.lr_rotation, "name": "node_q"},
             {"params": [self.node_t], "lr": sequence.lr_translation * self.extent,
              "name": "node_t"}], lr=0.0, fused=True)
        self.model = previous
        self._rows = self._rows_of = None  # `_moving_rows`' and the frozen mask it is of
        self.state: TrackedState | None = None
        self.strategy: DensifyStrategy | None = None

    # -- the start -----------------------------------------------------------------------------
    def _race_starts(self, earlier, earliest) -> tuple[dict, StartRace]:
        """The candidate starts (`core.sequence.starts.candidate_starts`) and the race that
        ordered them (`SequenceConfig.start_views`, `start_race`)."""
        s = self.seq
        pick = (lambda t: t) if self.rows is None else (lambda t: t[self.rows])
        earlier, earliest = ((None if e is None else (pick(e[0]), pick(e[1])))
                             for e in (earlier, earliest))
        starts = candidate_starts(self.graph, pick(self.previous.means.detach()), earlier,
                                  earliest, s.motion_candidates, s.second_order)
        posed: dict[str, DeformedGaussians] = {}

        def loss(name: str, index: int) -> float:
            if name not in posed:
                posed[name] = self._posed(*starts[name])
            return self._start_loss(posed[name], index)

        centres = torch.stack([c.center for c in self.cameras])
        race = race_starts(list(starts), loss, view_order(centres.cpu()), s.start_views,
                           s.start_race)
        return starts, race

    def _posed(self, rotations: Tensor, translations: Tensor) -> DeformedGaussians:
        """The previous frame's Gaussians moved by node parameters (the moving ones)."""
        return DeformedGaussians(self.previous, self.graph, rotations, translations, self.rows)

    @torch.no_grad()
    def _start_loss(self, posed: DeformedGaussians, index: int) -> float:
        """The image loss (photometric + silhouette) the first deform step would see on view
        `index` from the posed start, at its blur."""
        sigma = self.seq.coarse_sigma
        r = self.render_view(posed, index, self.plan)
        silhouette = self._silhouette(r, index, sigma)
        return float(self._photometric(r, index, self.background, sigma)) + (
            0.0 if silhouette is None else float(silhouette))

    # -- losses --------------------------------------------------------------------------------
    def _photometric(self, r, index: int, background: Tensor, sigma: float) -> Tensor:
        """The blurred photometric term alone (the start race's score)."""
        return photometric_loss(blur(r.rgb, sigma), blur(self.target(index, background), sigma),
                                self.config.losses)

    def _silhouette(self, r, index: int, sigma: float) -> Tensor | None:
        """`deform_mask` x mean |blur(alpha_c) - blur(mask)|; None without a mask (or weight)."""
        mask = self.views[index].mask
        if self.seq.deform_mask <= 0 or mask is None:
            return None
        return self.seq.deform_mask * coverage_l1(blur(r.alpha_c, sigma), blur(mask, sigma))

    def _image_terms(self, r, index: int, background: Tensor, sigma: float = 0.0,
                     ao: bool = False) -> dict:
        """`core.training.terms.image_terms` with the tracked frame's settings: the geometry
        mask term as `sequence.geometry_mask` says, the visibility term when `ao` (refine) and
        AO was baked."""
        ao_target = self.ao_targets[index] if ao and self.ao_targets is not None else None
        return image_terms(r, self.views[index], self.cameras[index],
                           self.target(index, background), self.plan, self.config.losses,
                           blur_sigma=sigma, mask_term=self.seq.geometry_mask,
                           ao_target=ao_target)

    # -- the stages ----------------------------------------------------------------------------
    def _deform_terms(self, index: int, bg: Tensor) -> tuple[dict, object]:
        s, k = self.seq, self.step
        decay = 0.1 ** (k / self.deform_steps)  # exponential, to a tenth by the stage's end
        for group, base in zip(self.optimizer.param_groups,
                               (s.lr_rotation, s.lr_translation * self.extent)):
            group["lr"] = base * decay
        posed = self._posed(self.node_q, self.node_t)
        sigma = blur_sigma(k, self.deform_steps, s.coarse_sigma)
        views = [(index, bg)] + [(i, self.step_background(i)) for i in
                                 (self.next_view() for _ in range(s.deform_views - 1))]
        terms: dict[str, Tensor] = {}
        first = None  # the step's own view (index), which StepInfo's PSNR compares
        for i, b in views:
            r = self.render_view(posed, i, self.plan, b)
            if first is None:
                first = r
            view_terms = self._image_terms(r, i, b, sigma)
            silhouette = self._silhouette(r, i, sigma)
            if silhouette is not None:
                view_terms["silhouette"] = silhouette
            for name, value in view_terms.items():
                terms[name] = terms.get(name, 0.0) + value / len(views)
        # Read in one go at the stage's end (no read-back a step); the two terms are added
        # on the host, in double precision, as they always were.
        self._pending_losses.append(torch.stack([
            terms["photometric"].detach(),
            terms.get("silhouette", torch.zeros((), device=self.device)).detach()]))
        terms.update(deform_losses(self.graph, self.node_q, self.node_t, arap=s.arap,
                                   quat_norm=s.quat_norm))
        return terms, first

    def _refine_terms(self, index: int, bg: Tensor) -> tuple[dict, object]:
        s = self.seq
        r = self.render_view(self.model, index, self.plan, bg)
        terms = self._image_terms(r, index, bg, ao=True)
        rows = self._moving_rows()
        if s.temporal:
            weights = TemporalWeights(s.temporal_opacity_g, s.temporal_means, s.temporal_quats,
                                      s.temporal_normals)
            terms.update(temporal_loss(self.model, self.state.anchor, weights, rows))
        if s.anisotropy > 0:
            scales = self.model.scales if rows is None else self.model.scales[rows]
            terms["anisotropy"] = anisotropy_loss(scales, s.anisotropy, s.anisotropy_ratio)
        return terms, r

    def _read_losses(self) -> list[float]:
        """`deform_losses`, the steps still on the device read back in one transfer."""
        if self._pending_losses:
            self.deform_losses += [a + b for a, b in torch.stack(self._pending_losses).tolist()]
            self._pending_losses = []
        return self.deform_losses

    def _moving_rows(self) -> Tensor | None:
        """Indices of the Gaussians the refine stage moves (None: all); recomputed only when
        densification or pruning changed the model (a `nonzero` waits for the device)."""
        if self.state.frozen is None:
            return None
        if self._rows_of is not self.state.frozen:
            self._rows, self._rows_of = (~self.state.frozen).nonzero()[:, 0], self.state.frozen
        return self._rows

    def _end_deform(self) -> None:
        self._read_losses()
        tail = self.deform_losses[-max(1, self.deform_steps // 6):]
        self.deform_loss = sum(tail) / max(len(tail), 1)

    def _start_refine(self, bake: bool = True) -> None:
        """The deformed Gaussians become the model; anchors, ids, optimizer, strategy start."""
        s, cfg = self.seq, self.config
        self.refine_steps = refine_steps(s, self.nominal_refine, self.deform_loss,
                                         self.reference_loss or self.refine_reference,
                                         self.refine_credit, self.scoring_extra)
        with torch.no_grad():
            self.model = self._posed(self.node_q, self.node_t).to_model()
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
                                  anchor=anchors_of(self.model), next_id=self.next_id,
                                  frozen=None if self.moving is None else ~self.moving)
        if bake and self.ao_baker is not None:
            start = time.perf_counter()
            self.ao_targets = to_device(list(self.ao_baker(self.model, self.cameras,
                                                           self.optimizer, self.plan.beta)),
                                        self.device)
            self.ao_seconds = time.perf_counter() - start

    # -- FrameFitter ---------------------------------------------------------------------------
    @property
    def iterations(self) -> int:
        return self.deform_steps + self.refine_steps

    @property
    def phase(self) -> str:
        """'deform' or 'refine': the stage of the next step."""
        return "deform" if self.step < self.deform_steps else "refine"

    def before_step(self) -> None:
        if self.step == self.deform_steps and self.state is None:
            if self.deform_loss is None:
                self._end_deform()
            self._start_refine()

    def step_terms(self, index: int, background: Tensor) -> tuple[dict, object, StagePlan]:
        deforming = self.step < self.deform_steps
        terms, r = (self._deform_terms if deforming else self._refine_terms)(index, background)
        return terms, r, self.plan

    def before_update(self) -> None:
        """The static scene gets no update (its Adam moments stay 0, so it does not move)."""
        if self.state is None or self.state.frozen is None:
            return
        frozen = self.state.frozen
        for p in self.model.params.values():
            if p.grad is not None:  # masked_fill: no boolean indexing, which waits for the device
                p.grad.masked_fill_(frozen.view(-1, *([1] * (p.grad.dim() - 1))), 0)

    def after_step(self, r, index: int, p: StagePlan) -> None:
        if self.state is None:
            return
        cam = self.cameras[index]
        self.strategy.update(self.state, r.raster, cam.width, cam.height)
        k = self.step - self.deform_steps + 1  # refine steps done
        if k % max(1, self.refine_steps // 4) == 0 and k < self.refine_steps:
            self.strategy.densify(self.model, self.optimizer, self.state, self.generator)
            relabel(self.state, self.model)
            prune_transparent(self.model, self.optimizer, self.state,
                              self.config.densify.transparent)
            self._moving_rows()  # now, in a step that waits anyway, not in the next one

    def current(self) -> tuple[object, StagePlan]:
        model = self.model if self.state is not None else self._posed(self.node_q, self.node_t)
        return model, self.plan

    def state_blob(self) -> dict:
        """Node parameters and the deform losses; in the refine stage the model, its tracked
        state and AO targets too (the graph is rebuilt from the previous frame,
        deterministically)."""
        blob = {"node_q": self.node_q.detach(), "node_t": self.node_t.detach(),
                "deform": {"losses": list(self._read_losses()), "loss": self.deform_loss}}
        if self.state is not None:
            blob.update(params={k: v.detach() for k, v in self.model.params.items()},
                        state=asdict(self.state), ao_targets=self.ao_targets)
        return blob

    def load_state_blob(self, blob: dict) -> None:
        with torch.no_grad():
            self.node_q.copy_(blob["node_q"])
            self.node_t.copy_(blob["node_t"])
        self.deform_losses = [float(x) for x in blob["deform"]["losses"]]
        self._pending_losses = []
        self.deform_loss = blob["deform"]["loss"]
        if "params" in blob:
            self._start_refine(bake=False)  # the targets come from the checkpoint
            self.model = GaussianModel(blob["params"]).to(self.device)
            self.optimizer = self.model.make_optimizer(self.config.rates, self.extent)
            self.state = TrackedState(**to_device(blob["state"], self.device))
            self.ao_targets = to_device(blob.get("ao_targets"), self.device)

    # -- what the run records ------------------------------------------------------------------
    def _scoring_renders(self) -> int:
        return (self.race.renders + 1) // 2

    @property
    def scoring_extra(self) -> int:
        """Scoring renders (as `renders` counts them) the start race took beyond scoring every
        start on `start_views` views; the refine stage pays them back, so a close race costs
        the run no more renders."""
        starts = len(self.race.views)
        base = starts * min(self.seq.start_views, len(self.views)) if starts > 1 else 0
        return max(0, self._scoring_renders() - (base + 1) // 2)

    @property
    def renders(self) -> int:
        """Images rendered and back-propagated in all: the frame's cost in key-frame steps. The
        start's scoring renders (forward only: about 40% of a training render's time) count
        half each, rounded up."""
        return (self.deform_steps * self.seq.deform_views + self.refine_steps
                + self._scoring_renders())

    @property
    def ids(self) -> Tensor:
        """(N,) track ids of the current model's Gaussians."""
        return self.prev_ids if self.state is None else self.state.ids

    @property
    def group_next_id(self) -> int:
        return self.next_id if self.state is None else self.state.next_id
