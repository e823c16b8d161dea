"""`FrameRecord`: what a run keeps of each finished frame, metrics.json's `frames[<frame>]`. A
tracked frame's inputs are planned from these records (`core.sequence.plan.GopPlan`), so a
resumed run, which always has metrics.json, plans what the uninterrupted one would."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

__all__ = ["FrameRecord"]


@dataclass
class FrameRecord:
    """One finished frame."""

    iterations: int
    """Optimisation steps of the frame."""
    renders: int
    """Images rendered and back-propagated (a tracked frame's cost in key-frame steps)."""
    seconds: float
    """Wall time of the frame, its outputs included."""
    train_seconds: float | None
    """Wall time of its fitting alone (steps and AO bake; the device waited for)."""
    extras_seconds: dict[str, float] | None
    """Wall time of what it writes after fitting, by output: ply, renders (the held-out views),
    mesh, evaluate (the training views' PSNR)."""
    ao_bake_seconds: float | None
    """Seconds its AO bake took (None: no bake)."""
    resumed_at: int
    """The step it resumed from (0: not resumed)."""
    gaussians: int
    train_psnr: float
    """Mean PSNR over the training views at the end."""
    normal_prior: str
    """Where the normal priors came from: capture, estimator, mixed or off."""
    stages: str
    """'static (key frame)' or 'deform + refine'."""
    gop: int
    """Index of its group of pictures."""
    position: int
    """Position inside the group (0: the key frame)."""
    next_track_id: int
    """The group's next unused track id after this frame."""
    final_losses: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    history: list[dict[str, Any]] = field(default_factory=list)
    """Per-step records (step, stage, Gaussians, PSNR, seconds, losses), thinned."""
    mesh: dict[str, Any] | None = None
    """The frame's mesh statistics (None: meshing off), or {"error": ...}."""
    seed_seconds: float | None = None
    """A key frame's: seconds its seeds took (the rig's depth included when they used it)."""
    rig_seconds: dict[str, float] | None = None
    """A key frame's: seconds of each part of its rig geometry (`core.rig.RigGeometry`:
    triangulation, stereo, priors) that it computed."""
    # A tracked frame's (None for a key frame):
    previous: str | None = None
    """The frame it was deformed from."""
    new_tracks: int | None = None
    """Tracks born in its refine stage."""
    start: dict[str, Any] | None = None
    """The start race: {"from": the start chosen, "scores", "views"}."""
    deform_loss: float | None = None
    """End loss of its deform stage (the next frame's reference)."""
    refine_steps: int | None = None
    refine_nominal: int | None = None
    scoring_extra: int | None = None
    """Renders its start race took beyond `start_views`, paid from the refine steps."""

    def to_json(self) -> dict[str, Any]:
        return asdict(self)
