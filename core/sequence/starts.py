"""Where a tracked frame's deform stage starts: candidate node parameters ("rest" and predictions
from the previous frames' motion, `core.sequence.motion`) and a race that picks one of them on
as few rendered views as the evidence allows.

A start is judged by the image loss (blurred photometric + silhouette) the deform stage's first
step would see from it. On one view that loss depends as much on the view as on the start: at
the walk's crossing phase a start can lead by 0.02 on one camera and trail by as much on the
next (docs/design.md), so four views picked the wrong start where all fourteen picked the right
one. The race (racing algorithms for model selection drop a candidate once the evidence separates
it, Maron and Moore's Hoeffding races, 1993; here the evidence is a paired t statistic) scores
every start on `first` views, then keeps adding views, a few at a time, to the leader and
to each rival not yet separated from it; a rival is dropped once its paired mean difference to
the leader over the same views is `t_stop` standard errors or more. Clear decisions stop after
the first views; close ones go on to every view. Views are taken in farthest-point order of the
camera centres, so each added view is the one least like those already scored.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from torch import Tensor

from core.sequence.graph import DeformationGraph, farthest_point_sampling
from core.sequence.motion import predict_node_motion, predict_node_motion_second_order

__all__ = ["StartRace", "candidate_starts", "race_starts", "view_order"]

VIEWS_PER_ROUND = 2
"""Views added per race round after the first (2 and 4 chose the same starts on the synthetic
sequence; 2 renders fewer)."""


@dataclass(frozen=True)
class StartRace:
    """How a race ended: `order` the start names, winner first (then the rivals still in the
    race by their mean, then the dropped ones, last dropped first); `scores` each start's mean
    loss over the views it was scored on; `views` how many that was; `renders` the forward
    renders it took (the sum of `views`)."""

    order: list[str]
    scores: dict[str, float]
    views: dict[str, int]

    @property
    def renders(self) -> int:
        return sum(self.views.values())


def view_order(centres: Tensor) -> list[int]:
    """Indices of cameras with centres (V, 3) in farthest-point order from camera 0: each next
    one the farthest from all before it (ties to the lowest index;
    `core.sequence.graph.farthest_point_sampling`)."""
    if centres.ndim != 2 or centres.shape[-1] != 3:
        raise ValueError(f"centres: expected (V, 3) camera centres, got {tuple(centres.shape)}")
    if len(centres) == 0:
        return []
    return farthest_point_sampling(centres.double(), len(centres)).tolist()


def _separated(diff: list[float], t_stop: float) -> bool:
    """Whether a rival whose per-view losses exceed the leader's by `diff` is t_stop standard
    errors behind (a rival no different on any view is dropped: it is the same start)."""
    n = len(diff)
    mean = sum(diff) / n
    if all(d == 0.0 for d in diff):
        return True
    if n < 2:
        return False
    var = sum((d - mean) ** 2 for d in diff) / (n - 1)
    if var <= 0.0:
        return mean > 0.0
    return mean / math.sqrt(var / n) >= t_stop


def race_starts(names: Sequence[str], loss: Callable[[str, int], float], views: Sequence[int],
                first: int, t_stop: float) -> StartRace:
    """Race the starts `names` (first: the one ties go to) over `views` (camera indices in the
    order to score them; `view_order`): each is scored on the first `first` views by
    `loss(name, view)`; with `t_stop` > 0, views are then added `VIEWS_PER_ROUND` at a time to
    the starts still in the race until one is left or every view is scored (module
    docstring). `t_stop` 0 scores the first views only. A single start is not scored."""
    names = list(names)
    if not names:
        raise ValueError("names: expected at least one start")
    if len(names) == 1:
        return StartRace(names, {}, {})
    if not views:
        raise ValueError("views: expected at least one view to score the starts on")
    if t_stop < 0:
        raise ValueError(f"t_stop: expected >= 0, got {t_stop}")
    losses: dict[str, list[float]] = {n: [] for n in names}
    alive, dropped = list(names), []
    used = min(max(1, first), len(views))
    while True:
        for n in alive:
            for v in views[len(losses[n]):used]:
                losses[n].append(float(loss(n, v)))
        mean = {n: sum(losses[n]) / len(losses[n]) for n in alive}
        leader = min(alive, key=lambda n: (mean[n], names.index(n)))
        for n in [n for n in alive if n != leader]:
            diff = [a - b for a, b in zip(losses[n], losses[leader])]
            if t_stop <= 0 or _separated(diff, t_stop):
                alive.remove(n)
                dropped.append(n)
        if len(alive) == 1 or used >= len(views) or t_stop <= 0:
            break
        used = min(used + VIEWS_PER_ROUND, len(views))
    if t_stop <= 0:  # no race: every start was scored on the same views
        order = sorted(names, key=lambda n: (mean[n], names.index(n)))
    else:
        order = sorted(alive, key=lambda n: (mean[n], names.index(n))) + dropped[::-1]
    return StartRace(order, {n: sum(v) / len(v) for n, v in losses.items()},
                     {n: len(v) for n, v in losses.items()})


def candidate_starts(graph: DeformationGraph, current: Tensor,
                     earlier: tuple[Tensor, Tensor] | None,
                     earliest: tuple[Tensor, Tensor] | None,
                     motion_candidates: Sequence[float],
                     second_order: Sequence[float]) -> dict[str, tuple[Tensor, Tensor]]:
    """Node parameters to start a deform stage from, by name: "rest"; with `earlier` (positions
    (N, 3) and known (N,) of the graph's Gaussians one frame before `current` (N, 3)) the
    previous motion continued at each damping a of `motion_candidates` ("damped a"); with
    `earliest` (two frames before) too its second-order prediction at each c of
    `second_order` ("second-order c")."""
    starts = {"rest": graph.identity()}
    if earlier is not None:
        for a in motion_candidates:
            starts[f"damped {a:g}"] = predict_node_motion(graph, current, *earlier,
                                                          damping=float(a))
    if earlier is not None and earliest is not None:
        known = earlier[1] & earliest[1]
        for c in second_order:
            starts[f"second-order {c:g}"] = predict_node_motion_second_order(
                graph, current, earlier[0], earliest[0], known, c=float(c))
    return starts
