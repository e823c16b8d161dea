"""Groups of pictures: the selected frames cut into runs of `gop` frames, the first of each a key
frame (full static stages), the others deformed from their predecessor (DESIGN.md section 5)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["Gop", "FrameRole", "roles", "roles_of", "segment", "with_rekeys"]


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
    return roles_of(segment(frames, gop))


def with_rekeys(frames: Sequence[str], gop: int, rekeyed: set[str] | frozenset[str]) -> list[Gop]:
    """`segment`, where each frame of `rekeyed` (made a key frame after its tracking was lost,
    `SequenceConfig.rekey_loss_ratio`) also starts a group; groups are numbered in order."""
    groups: list[list[str]] = []
    for g in segment(frames, gop):
        for p, frame in enumerate(g.frames):
            if p == 0 or frame in rekeyed:
                groups.append([])
            groups[-1].append(frame)
    return [Gop(i, tuple(fs)) for i, fs in enumerate(groups)]


def roles_of(groups: Sequence[Gop]) -> list[FrameRole]:
    """Every frame's role in `groups`, in order."""
    return [FrameRole(frame, g.index, p, g.frames[p - 1] if p else None)
            for g in groups for p, frame in enumerate(g.frames)]
