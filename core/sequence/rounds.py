"""The deform stage's rounds: where each starts, how it ended, whether another follows, which is
kept. Explicit state (a checkpoint holds `state_dict()`), no rendering: `FrameTracker` feeds it
each step's image loss and asks it at the end of every round.

Starts are node parameters by name ("rest", or a prediction from the previous frames' motion,
`core.sequence.motion`), ordered before training (by a score, lower is better, or by the race
of `core.sequence.starts`); round
r starts from the r-th while there are starts left, else from where the previous round ended.
A round's end loss is the mean image loss of its last sixth of steps (the blur is gone by
then). A round that ends at `retry_loss_ratio` times the previous frame's end loss or more is
followed by another while `deform_retries` allow; then the round that ended lowest is kept and
its end loss becomes the frame's `deform_loss`, the next frame's reference.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

__all__ = ["DeformRounds", "RoundEnd"]


@dataclass(frozen=True)
class RoundEnd:
    """What to do when a round ends: `retry` another round from `start` (None: from where this
    one ended), or keep the node parameters `q`, `t` and go on to the refine stage."""

    retry: bool
    start: tuple[Tensor, Tensor] | None = None
    q: Tensor | None = None
    t: Tensor | None = None
    note: str = ""


class DeformRounds:
    """Bookkeeping of one frame's deform rounds (module docstring)."""

    def __init__(self, starts: dict[str, tuple[Tensor, Tensor]], scores: dict[str, float],
                 round_steps: int, *, reference_loss: float | None, retries: int,
                 ratio: float, order: list[str] | None = None):
        if set(scores) - set(starts):
            raise ValueError("scores: every scored start needs node parameters")
        if order is not None and sorted(order) != sorted(starts):
            raise ValueError(f"order: expected the start names {sorted(starts)}, got {order}")
        self.starts, self.scores = starts, scores
        self.order = (list(order) if order is not None
                      else sorted(scores, key=scores.get) if scores else list(starts))
        """Start names best first: `order` when given (a race's, `core.sequence.starts`), else
        by score (in `starts`' order when nothing was scored)."""
        self.round_steps, self.reference_loss = round_steps, reference_loss
        self.max_retries, self.ratio = retries, ratio
        self.retries = 0
        """Rounds added so far."""
        self.ended: list[tuple[float, Tensor, Tensor]] = []
        """Finished rounds: (end loss, node quaternions, node translations)."""
        self.losses: list[float] = []
        """The current round's per-step image losses."""
        self.kept: int | None = None
        """Index of the kept round once the stage is over."""

    def first(self) -> tuple[Tensor, Tensor]:
        """Node parameters of the first round's start."""
        return self.starts[self.order[0]]

    def record(self, image_loss: float) -> None:
        self.losses.append(float(image_loss))

    def end(self, q: Tensor, t: Tensor) -> RoundEnd:
        """The current round ended with node parameters `q`, `t`."""
        tail = self.losses[-max(1, self.round_steps // 6):]
        loss = sum(tail) / max(len(tail), 1)
        self.ended.append((loss, q.detach().clone(), t.detach().clone()))
        self.losses = []
        behind = self.reference_loss is not None and loss >= self.ratio * self.reference_loss
        if behind and self.retries < self.max_retries:
            self.retries += 1
            name = self.order[self.retries] if self.retries < len(self.order) else None
            note = (f"deform round {self.retries + 1} from "
                    + ("where round 1 ended" if name is None else f"start {name}")
                    + f": round {self.retries} ended at {loss / self.reference_loss:.2f}x the "
                      "previous frame's loss")
            return RoundEnd(True, None if name is None else self.starts[name], note=note)
        self.kept = min(range(len(self.ended)), key=lambda r: self.ended[r][0])
        _, q_best, t_best = self.ended[self.kept]
        return RoundEnd(False, q=q_best, t=t_best)

    @property
    def deform_loss(self) -> float | None:
        """End loss of the kept round (None before the stage is over)."""
        return None if self.kept is None else self.ended[self.kept][0]

    @property
    def start(self) -> str:
        """Name of the start the kept (or current) round began from; a round that went on from
        where another ended counts that one's start."""
        index = self.retries if self.kept is None else self.kept
        return self.order[min(index, len(self.order) - 1)]

    def state_dict(self) -> dict:
        return {"retries": self.retries, "ended": list(self.ended), "losses": list(self.losses),
                "kept": self.kept}

    def load_state_dict(self, state: dict) -> None:
        self.retries = int(state["retries"])
        self.ended = [(float(e), q, t) for e, q, t in state["ended"]]
        self.losses = [float(x) for x in state["losses"]]
        self.kept = None if state["kept"] is None else int(state["kept"])
