"""Rate control of a sequence's refine steps (`SequenceConfig.refine_adapt`): how many a tracked
frame runs, and how many the run's earlier frames left it. Steps are spent where a frame tracked
worse than its predecessor, at a constant budget over the run, as a video encoder spends bits
where the picture needs them. Pure functions of numbers and metrics.json's frame records, so a
resumed run (metrics.json is always on disk) spends what the uninterrupted one would.
"""

from __future__ import annotations

import numpy as np

from core.config import SequenceConfig

__all__ = ["median_deform_loss", "refine_credit", "refine_steps"]


def refine_steps(seq: SequenceConfig, nominal: int, end_loss: float | None,
                 reference: float | None, credit: int, scoring_extra: int = 0) -> int:
    """Refine steps of a frame whose deform stage ended at `end_loss`: the nominal times
    (end_loss / reference) ** refine_adapt (`refine_second` without a reference), clipped to
    [`refine_min`, `refine_max`] x nominal, at most the nominal plus `credit` less
    `scoring_extra` (the renders its start race took beyond `start_views`), and at least
    `refine_floor`. The nominal when refine_adapt is 0 or the stage has no end loss."""
    if seq.refine_adapt <= 0 or end_loss is None:
        return nominal
    scale = (end_loss / reference) ** seq.refine_adapt if reference else seq.refine_second
    want = round(nominal * min(max(scale, seq.refine_min), seq.refine_max))
    return max(seq.refine_floor(nominal), min(want, nominal + credit - scoring_extra))


def median_deform_loss(frames: dict[str, dict]) -> float | None:
    """Median end loss of the deform stages of the finished tracked frames of `frames`
    (metrics.json's), None before the
    first: what a group's second frame, which follows a key frame, compares its own with
    (`SequenceConfig.refine_adapt`)."""
    losses = [m["deform_loss"] for m in frames.values()
              if m.get("deform_loss") is not None and m.get("refine_steps") is not None]
    return float(np.median(losses)) if losses else None


def refine_credit(frames: dict[str, dict], remaining: int, nominal: int, floor: int) -> int:
    """Refine steps the next tracked frame may run beyond `nominal`: what the finished tracked
    frames of `frames` (metrics.json's) left unused (nominal minus run, less the renders their
    start races took beyond `start_views`; negative where they borrowed), plus what the
    `remaining` tracked frames after it can still pay back at `floor` steps each. Every frame
    keeping within it leaves the run's tracked frames at no more than `nominal` refine steps
    (and the nominal scoring) on average."""
    saved = sum(m["refine_nominal"] - m["refine_steps"] - (m.get("scoring_extra") or 0)
                for m in frames.values()
                if m.get("refine_steps") is not None and m.get("refine_nominal") is not None)
    return saved + remaining * (nominal - floor)
