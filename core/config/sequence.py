"""How the frames after a group's key frame are deformed and refined (docs/design.md,
"Sequences", gives the measurement behind each default)."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import Field

from core.config.base import Fraction, Positive, Weight, section

__all__ = ["SequenceConfig"]

Share = Annotated[float, Field(ge=0, le=10)]
"""A fraction of a key frame's iterations."""
Damping = Annotated[float, Field(gt=0, le=2)]
Cosine = Annotated[float, Field(ge=-1, le=1)]


@section
class SequenceConfig:
    """The sequential method's settings. Step counts are fractions of the key frame's
    iterations, so every preset scales the same plan."""

    enabled: bool = True
    """Deform + refine the frames after each group's first; off: every frame is a key frame."""
    key_steps: Annotated[float, Field(ge=0.1, le=10)] = 2.0
    """A group of several frames starts from a key frame trained this many times the
    schedule's iterations (every step count scaled; a frame alone keeps the schedule);
    tracked frames' steps stay fractions of the nominal. 2: the key frame is no longer the
    weakest of its group, so a boundary between groups drops no more than a tracked frame
    (docs/design.md 5.9)."""
    deform_fraction: Share = 0.2
    """Deform-stage steps per frame, as a fraction of a key frame's iterations."""
    refine_fraction: Share = 0.28
    """Nominal refine-stage steps per frame, as a fraction of a key frame's iterations
    (`refine_adapt` moves it per frame)."""
    num_nodes: Annotated[int, Field(ge=5, le=65_536)] = 1024
    """Deformation-graph nodes at most (farthest-point samples of the previous frame)."""
    gaussians_per_node: Annotated[int, Field(ge=1, le=10_000_000)] = 32
    """Small models get fewer nodes: one per this many Gaussians (at least 5)."""
    node_neighbors: Annotated[int, Field(ge=1, le=64)] = 8
    """ARAP neighbours of each node."""
    motion_candidates: Annotated[tuple[Damping, ...], Field(max_length=8)] = (1.0,)
    """Starts besides rest, as dampings of the previous frame's motion (from a group's third
    frame on); the start with the lowest loss wins."""
    second_order: Annotated[tuple[Cosine, ...], Field(max_length=8)] = (0.5,)
    """Second-order starts 2c d_t - d_(t-1), one per c (from a group's fourth frame on)."""
    start_views: Annotated[int, Field(ge=1, le=4096)] = 4
    """Training views that score every candidate start first."""
    start_race: Annotated[float, Field(ge=0, le=1e9)] = 2.0
    """Standard errors of the paired per-view difference by which a rival must trail the
    leading start before it stops being scored on more views; 0: `start_views` only."""
    lr_rotation: Annotated[float, Field(gt=0, le=1)] = 2e-2
    """Adam rate of the node quaternions (decays exponentially to a tenth over the stage)."""
    lr_translation: Annotated[float, Field(gt=0, le=1)] = 1e-2
    """Adam rate of the node translations, times the scene extent."""
    arap: Weight = 0.02
    """Weight of the ARAP term (edge residuals relative to the mean edge length)."""
    quat_norm: Weight = 1.0
    """Weight of the node-quaternion unit-norm term."""
    coarse_sigma: Annotated[float, Field(ge=0, le=64)] = 4.0
    """Deform stage: render and target blurred by this many pixels at the first step,
    shrinking to none by the stage's middle; 0: off."""
    deform_views: Annotated[int, Field(ge=1, le=64)] = 1
    """Deform stage: training views whose losses are averaged in each step."""
    deform_mask: Weight = 1.0
    """Deform stage: weight of the silhouette L1 (blurred coverage against the blurred mask)."""
    refine_adapt: Annotated[float, Field(ge=0, le=10)] = 3.0
    """Refine steps = nominal x r ** refine_adapt, r the deform loss over the previous frame's,
    within [`refine_min`, `refine_max`] and the run's credit; 0: fixed."""
    refine_min: Annotated[float, Field(gt=0, le=1)] = 0.85
    """Fewest refine steps, as a multiple of the nominal."""
    refine_max: Annotated[float, Field(ge=1, le=10)] = 2.0
    """Most refine steps, as a multiple of the nominal."""
    refine_borrow: Annotated[int, Field(ge=0, le=1000)] = 1
    """Most tracked frames ahead a run may borrow refine steps against; 0: spend only savings."""
    refine_second: Annotated[float, Field(ge=0, le=10)] = 2.0
    """Refine steps a second frame without a reference asks, as a multiple of the nominal."""
    refine_scope: Literal["group", "run"] = "group"
    """What a frame's refine budget draws on: its own group's frames (groups independent, so
    they run in parallel to the same result) or the whole run's (each group waits for the
    one before)."""
    temporal: bool = True
    """Refine stage: temporal L1 to the deformed values."""
    temporal_opacity_g: Weight = 0.01
    """Temporal weight of the geometry opacity."""
    temporal_means: Weight = 1.0
    """Temporal weight of the positions."""
    temporal_quats: Weight = 0.3
    """Temporal weight of the rotations."""
    temporal_normals: Weight = 0.5
    """Temporal weight of the normals."""
    anisotropy: Weight = 0.01
    """Weight of the anisotropy loss mean(max(s_max / s_min - r, 0))."""
    anisotropy_ratio: Annotated[float, Field(ge=1, le=1000)] = 3.0
    """Largest scale ratio r the anisotropy loss leaves alone."""
    means_lr_scale: Positive = 3.0
    """Refine stage: position rate = this x the key frame's initial rate (no decay)."""
    max_growth: Fraction = 0.02
    """Refine stage: densification (four times a stage) adds at most this fraction of the
    frame's Gaussians."""
    bake_ao: bool = False
    """Refine stage: re-bake ambient occlusion of the deformed pose (visibility loss on)."""
    geometry_mask: bool = False
    """Tracked frames: the geometry mask loss of the key frame (`losses.geometry_mask`) on
    views with a matte; off, as tracked frames have always been fitted."""
    moving: Literal["auto", "all", "subject"] = "auto"
    """What a tracked frame moves: `all` its Gaussians; `subject` those inside the subject
    masks' hull (`core.sequence.hull`) of this frame or the one before, while the rest of the
    scene stays exactly as the key frame made it (nothing to fit, nothing to store, no drift);
    `auto`: subject where the masks mark a subject inside a scene (`train.masks` subject),
    all where they cut it out."""
    hull_dilate: Annotated[int, Field(ge=0, le=256)] = 4
    """Subject hull: masks grown by this many pixels at the training resolution (the rim,
    and motion since the masks)."""
    hull_share: Annotated[float, Field(gt=0, le=1)] = 0.8
    """Subject hull: a Gaussian is the subject's when inside this share of the masked views
    that see it (one wrong mask cannot cut a limb off)."""

    def nodes(self, gaussians: int) -> int:
        """Graph nodes for a model of `gaussians` Gaussians."""
        return max(5, min(self.num_nodes, gaussians // max(self.gaussians_per_node, 1)))

    def refine_floor(self, nominal: int) -> int:
        """Fewest refine steps of an adapted frame (`refine_min` x `nominal`, rounded up)."""
        return max(1, math.ceil(self.refine_min * nominal - 1e-9))

    def steps(self, key_iterations: int) -> tuple[int, int]:
        """(deform, refine) steps for a key frame of `key_iterations`; at least 1 each."""
        return (max(1, round(self.deform_fraction * key_iterations)),
                max(1, round(self.refine_fraction * key_iterations)))
