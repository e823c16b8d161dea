"""The refine stage's losses and its correspondence bookkeeping (docs/design.md section 5, Sequence).

- Temporal L1 to the deformed values ("anchors"), per attribute: geometry opacity 0.01,
  position 1.0, rotation 0.3, normal 0.5; rotations compared as unit quaternions on the anchor's
  hemisphere, normals as unit vectors, opacity activated.
- Anisotropy: 0.01 * mean(max(s_max / s_min - 3, 0)), which keeps Gaussians from turning into
  needles that the next frame's deformation would tear.
- Correspondence: every Gaussian has a track id, equal for the same Gaussian in consecutive frames
  of a group. Densification and pruning go through `DensifyStrategy`, whose state re-indexes every
  per-Gaussian tensor through `StrategyState.select`, new rows inheriting their parent's row;
  `TrackedState` rides on that to carry ids and anchors, and `relabel` then gives every row that
  repeats an earlier row's id (a clone's copy, a split's second sample) a fresh id and anchors
  equal to its own values at birth. A split's first sample keeps the parent's id.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from core.model import GaussianModel
from core.strategy import StrategyState

__all__ = ["ANCHORED", "TemporalWeights", "TrackedState", "anchors_of", "anisotropy_loss",
           "prune_transparent", "relabel", "temporal_loss"]

ANCHORED = ("means", "quats", "normals", "opacity_g")


@dataclass(frozen=True)
class TemporalWeights:
    """Per-attribute weights of the temporal L1 (docs/design.md section 5)."""

    opacity_g: float = 0.01
    means: float = 1.0
    quats: float = 0.3
    normals: float = 0.5


@torch.no_grad()
def anchors_of(model: GaussianModel) -> dict[str, Tensor]:
    """The values the temporal L1 compares with: means, unit quaternions, unit normals and the
    activated geometry opacity, detached."""
    return {"means": model.means.detach().clone(), "quats": model.quats.detach().clone(),
            "normals": model.normals.detach().clone(),
            "opacity_g": model.opacity_g.detach().clone()}


def temporal_loss(model: GaussianModel, anchor: dict[str, Tensor],
                  weights: TemporalWeights = TemporalWeights(),
                  rows: Tensor | None = None) -> dict[str, Tensor]:
    """The weighted L1 terms {name: w * mean |value - anchor|} (means over Gaussians and
    components; over `rows` alone when given). A quaternion q and -q are one rotation: q is
    compared after flipping it onto the anchor's hemisphere."""
    n = len(model)
    for name in ANCHORED:
        if anchor[name].shape[0] != n:
            raise ValueError(f"anchor[{name!r}]: expected {n} rows like the model, got "
                             f"{anchor[name].shape[0]}")
    pick = (lambda t: t) if rows is None else (lambda t: t[rows])
    a = {k: pick(v) for k, v in anchor.items()}
    q = pick(model.quats)
    sign = torch.where((q * a["quats"]).sum(dim=1, keepdim=True) < 0, -1.0, 1.0)
    return {
        "temporal_means": weights.means * (pick(model.means) - a["means"]).abs().mean(),
        "temporal_quats": weights.quats * (q * sign - a["quats"]).abs().mean(),
        "temporal_normals": weights.normals * (pick(model.normals) - a["normals"]).abs().mean(),
        "temporal_opacity_g": weights.opacity_g * (pick(model.opacity_g)
                                                   - a["opacity_g"]).abs().mean(),
    }


def anisotropy_loss(scales: Tensor, weight: float = 0.01, ratio: float = 3.0) -> Tensor:
    """weight * mean(max(s_max / s_min - ratio, 0)) over activated scales (N, 3)."""
    if scales.dim() != 2 or scales.shape[1] != 3:
        raise ValueError(f"scales: expected shape (N, 3), got {tuple(scales.shape)}")
    r = scales.max(dim=1).values / scales.min(dim=1).values.clamp_min(1e-12)
    return weight * (r - ratio).clamp_min(0).mean()


@dataclass
class TrackedState(StrategyState):
    """`StrategyState` plus each Gaussian's track id and temporal anchors, re-indexed with it."""

    ids: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.long))
    """(N,) int64 track ids."""
    anchor: dict[str, Tensor] = field(default_factory=dict)
    """Per-attribute (N, ...) anchors of the temporal L1."""
    next_id: int = 0
    """The next unused track id of the group."""
    born: int = 0
    """Gaussians given a fresh id in this frame."""

    def select(self, index: Tensor) -> None:
        super().select(index)
        self.ids = self.ids[index]
        self.anchor = {k: v[index] for k, v in self.anchor.items()}


@torch.no_grad()
def relabel(state: TrackedState, model: GaussianModel) -> int:
    """After densification: rows repeating an earlier row's id get fresh ids and anchors equal to
    their current values (no deformed value exists for them). Returns how many."""
    ids = state.ids.cpu().numpy()
    _, first = np.unique(ids, return_index=True)
    repeat = np.ones(len(ids), dtype=bool)
    repeat[first] = False
    count = int(repeat.sum())
    if count:
        rows = torch.from_numpy(repeat).to(state.ids.device)
        state.ids[rows] = torch.arange(state.next_id, state.next_id + count,
                                       device=state.ids.device)
        state.next_id += count
        state.born += count
        fresh = anchors_of(model)
        for name in ANCHORED:
            state.anchor[name][rows] = fresh[name][rows]
    return count


@torch.no_grad()
def prune_transparent(model: GaussianModel, optimizer, state: TrackedState,
                      threshold: float = 0.005) -> int:
    """Drop Gaussians below `threshold` opacity in both branches (never all, never
    `state.frozen` ones); returns how many."""
    drop = (model.opacity_c < threshold) & (model.opacity_g < threshold)
    if state.frozen is not None:
        drop &= ~state.frozen
    if bool(drop.all()):
        drop[model.opacity_c.argmax()] = False
    if bool(drop.any()):
        model.keep(~drop, optimizer)
        state.select(~drop)
    return int(drop.sum())
