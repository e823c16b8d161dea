"""The plan of a sequence (docs/design.md section 5.9.1): the selected frames cut into groups of
pictures of `gop` frames (`core.config.groups`), the first of each a key frame (static stages),
the others deformed from their predecessor; what each tracked frame starts from and may spend
(`TrackedInputs`, from the finished frames' records, so a resumed run plans what the
uninterrupted one would); and RUN/sequence.json, derived from the same records."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from core.config import SequenceConfig
from core.config.groups import FrameRole, frames_per_group, roles, segment
from core.sequence.budget import median_deform_loss, refine_credit

__all__ = ["GopPlan", "TrackedInputs"]


@dataclass(frozen=True)
class TrackedInputs:
    """What a tracked frame takes from the finished frames before it."""

    previous: str
    """The frame it is deformed from."""
    earlier: str | None
    """The frame before that in the group (its motion is continued), if any."""
    earliest: str | None
    """The one before that (second-order starts), if any."""
    next_id: int
    """The group's next unused track id."""
    reference_loss: float | None
    """The previous frame's deform loss (None after a key frame)."""
    refine_reference: float | None
    """Where there is no `reference_loss`: the run's median tracked deform loss (None before
    the first tracked frame)."""
    refine_credit: int
    """Refine steps the frame may run beyond the nominal (`core.sequence.budget`)."""


class GopPlan:
    """The roles of a run's frames and the inputs of each tracked frame."""

    def __init__(self, frames: Sequence[str], gop: int, sequence: SequenceConfig,
                 key_iterations: int):
        self.frames, self.sequence = list(frames), sequence
        self.gop = frames_per_group(gop, sequence)
        self.roles = roles(self.frames, self.gop)
        self.nominal = sequence.steps(key_iterations)[1]

    def inputs(self, index: int, records: dict[str, dict]) -> TrackedInputs | None:
        """The inputs of the `index`-th frame from the finished frames' records (metrics.json's
        frames); None for a key frame."""
        role = self.roles[index]
        if role.key:
            return None
        seq, before = self.sequence, records[role.previous]
        reference = before.get("deform_loss")
        later = [r for r in self.roles[index + 1:] if not r.key]
        if seq.refine_scope == "group":
            # Groups are independent: each spends only what its own frames saved or can pay
            # back, so groups run in parallel to the same result as one after another.
            records = {r.frame: records[r.frame] for r in self.roles
                       if r.gop == role.gop and r.frame in records}
            later = [r for r in later if r.gop == role.gop]
        earlier = before.get("previous")
        return TrackedInputs(
            previous=role.previous, earlier=earlier,
            earliest=None if earlier is None else records[earlier].get("previous"),
            next_id=before["next_track_id"], reference_loss=reference,
            refine_reference=None if reference is not None else median_deform_loss(records),
            refine_credit=refine_credit(records, min(seq.refine_borrow, len(later)),
                                        self.nominal, seq.refine_floor(self.nominal)))

    def record(self, records: dict[str, dict]) -> dict:
        """The content of RUN/sequence.json from the finished frames' records."""
        rows = [_row(r, records.get(r.frame)) for r in self.roles]
        done = [r for r in rows if r["done"]]

        def mean(role: str, key: str) -> float | None:
            vals = [r[key] for r in done if r["role"] == role and r[key] is not None]
            return round(float(np.mean(vals)), 3) if vals else None

        return {
            "version": 1, "gop": self.gop, "method": "deform + refine" if self.sequence.enabled
            else "independent (every frame a key frame)",
            "frames": rows,
            "gops": [{"index": g.index, "key": g.key, "frames": list(g.frames)}
                     for g in segment(self.frames, self.gop)],
            "timings": {"seconds_total": round(sum(r["seconds"] or 0 for r in done), 3),
                        "seconds_per_key_frame": mean("key", "seconds"),
                        "seconds_per_deformed_frame": mean("deformed", "seconds")},
            "gaussians": {"mean": None if not done else round(float(np.mean(
                [r["gaussians"] for r in done])), 1),
                          "per_key_frame": mean("key", "gaussians"),
                          "per_deformed_frame": mean("deformed", "gaussians")},
        }


def _row(role: FrameRole, m: dict | None) -> dict:
    """A frame's line of sequence.json (`m`: its record, None while it is not finished)."""
    m = m or {}
    start = m.get("start") or {}
    return {"frame": role.frame, "gop": role.gop, "position": role.position,
            "role": "key" if role.key else "deformed", "previous": role.previous,
            "done": bool(m), "gaussians": m.get("gaussians"), "seconds": m.get("seconds"),
            "iterations": m.get("iterations"),
            # Refine steps run (`refine_adapt` moves them off the nominal).
            "refine_steps": m.get("refine_steps"), "new_tracks": m.get("new_tracks"),
            # The start the deform stage began from, and the views the race scored it on.
            "start": start.get("from"),
            "start_views": (start.get("views") or {}).get(start.get("from"))}
