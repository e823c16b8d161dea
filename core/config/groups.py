"""How a run's frames are grouped (docs/design.md 4.4, 5.9.1): groups of pictures of `gop`
frames, the first of each a key frame, and which groups can run on their own (one part of a
sequence job each). Torch-free: the API splits a job into parts with these before it exists,
and `core.sequence.GopPlan` plans the frames with the same groups.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from core.config.run import RunConfig
from core.config.sequence import SequenceConfig

__all__ = ["FrameRole", "Gop", "frames_per_group", "independent_groups", "roles", "segment"]


@dataclass(frozen=True)
class Gop:
    """One group of pictures."""

    index: int
    """Position of the group in the run (0-based)."""
    frames: tuple[str, ...]
    """Its frames in order; the first is the key frame."""

    @property
    def key(self) -> str:
        return self.frames[0]


@dataclass(frozen=True)
class FrameRole:
    """What a frame is in the sequence."""

    frame: str
    gop: int
    """Index of its group."""
    position: int
    """Position inside the group (0: the key frame)."""
    previous: str | None
    """The frame it is deformed from (None for a key frame)."""
    size: int = 1
    """Frames in its group."""

    @property
    def key(self) -> bool:
        return self.position == 0


def segment(frames: Sequence[str], gop: int) -> list[Gop]:
    """Cut `frames` (in order) into groups of `gop` frames; the last may be shorter."""
    if not isinstance(gop, int) or isinstance(gop, bool) or gop < 1:
        raise ValueError(f"gop: expected an integer >= 1, got {gop!r}")
    frames = list(frames)
    if len(set(frames)) != len(frames):
        raise ValueError("frames: expected distinct frame names")
    return [Gop(i, tuple(frames[s:s + gop])) for i, s in enumerate(range(0, len(frames), gop))]


def roles(frames: Sequence[str], gop: int) -> list[FrameRole]:
    """Every frame's role, in order (`gop` 1: every frame a key frame)."""
    return [FrameRole(frame, g.index, p, g.frames[p - 1] if p else None, len(g.frames))
            for g in segment(frames, gop) for p, frame in enumerate(g.frames)]


def frames_per_group(gop: int, sequence: SequenceConfig) -> int:
    """The frames of a group: `gop`, or 1 when `sequence.enabled` is off (every frame is
    reconstructed on its own)."""
    return gop if sequence.enabled else 1


def independent_groups(frames: Sequence[str], cfg: RunConfig) -> list[Gop] | None:
    """The groups of a run of `frames` with `cfg`, when each can run on its own (a part of a
    sequence job); None when they cannot (`sequence.refine_scope` "run": a group spends what
    earlier groups saved, so it must wait for them)."""
    if cfg.sequence.enabled and cfg.sequence.refine_scope != "group":
        return None
    return segment(frames, frames_per_group(cfg.gop, cfg.sequence))
