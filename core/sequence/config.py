"""Configuration of the sequential method (DESIGN.md section 5, Sequence)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

__all__ = ["SequenceConfig"]


@dataclass(frozen=True)
class SequenceConfig:
    """How the frames after a GoP's key frame are deformed and refined. Step counts are fractions
    of the key frame's iterations, so every preset scales the same plan."""

    enabled: bool = True
    """Deform + refine the frames after each GoP's first; off: every frame is a key frame
    (independent per-frame reconstruction)."""
    deform_fraction: float = 0.2
    """Deform-stage steps per frame, as a fraction of a key frame's iterations (0.2 with 1
    view a step, 0.28 of refinement and 4 start views: a tracked frame renders half a key
    frame's images)."""
    refine_fraction: float = 0.28
    """Refine-stage steps per frame, as a fraction of a key frame's iterations (the nominal:
    `refine_adapt` moves it). Measured on the synthetic sequence, four training seeds at half a
    key frame's renders: deform 0.19 x 2 views + refine 0.1 gave 21.15 dB, deform 0.2 x 1
    view + refine 0.28 (with `coarse_sigma` 4) 21.85 dB; the refinement is what brings a
    tracked frame back to key-frame sharpness (docs/benchmarks.md)."""
    num_nodes: int = 1024
    """Deformation-graph nodes (farthest-point samples of the previous frame's Gaussians), at
    most; see `gaussians_per_node`."""
    gaussians_per_node: int = 32
    """Small models get fewer nodes, one per this many Gaussians (at least 5): a node seen by
    only a few Gaussians gets a noisy gradient and converges slowly (measured on the synthetic
    sequence: 128 nodes for 4000 Gaussians reach in 60 steps what 1024 do not in 300)."""
    node_neighbors: int = 8
    """ARAP neighbours of each node."""
    motion_candidates: tuple[float, ...] = (1.0,)
    """Deform stage: starts to try besides rest, as dampings of the previous frame's motion
    (fitted per node from the two frames before, `core.sequence.motion`): 1 continues it, 0.5
    half of it. The start whose blurred photometric + silhouette loss over the training views
    is lowest wins (rest included; `start_views`, `start_race`), so a limb that reverses or
    stops costs no overshoot. Used from a group's third frame on (the second has no motion
    to continue); () and no `second_order` never predict. ((0.5, 1) before the second-order
    starts: beside them, 0.5 won 1 frame of 44 on the synthetic sequence.)"""
    second_order: tuple[float, ...] = (0.5,)
    """Deform stage: from a group's fourth frame on (three frames of history), more starts:
    second-order predictions, each tracked Gaussian's next displacement 2c d_t - d_{t-1}
    (`core.sequence.motion.predict_node_motion_second_order`) for each c here. The recurrence
    holds exactly for any sinusoidal swing of w radians a frame with c = cos(w), and c = 1 is
    a constant acceleration. On the synthetic walk (0.9 rad a frame; the knees bend at another
    phase) 0.5 predicts the ground-truth vertices best (of c = 1, 0.8, 0.62, 0.5 and 0.3, it is
    the lowest in every frame from the fourth on), and at the legs' crossing phase it is the
    start that keeps them from swapping (docs/method.md); c = 1 never won beside it. Slow
    motion against the frame rate (c near 1) is what `motion_candidates` 1 already continues.
    () keeps the first-order starts only."""
    start_views: int = 4
    """Training views that score every candidate start first (in farthest-point order of the
    camera centres, `core.sequence.starts.view_order`); each costs a render without gradient
    per candidate. Scores are taken at the first step's blur (`coarse_sigma`): scored at 2 px
    under a 4 px stage, the predicted motion won more often (rest in 49% of frames against
    61%) but tracked worse over four seeds (largest drops 3.4-8.5 dB against 2.4-3.5)."""
    start_race: float = 2.0
    """After `start_views`, views are added two at a time to the starts not yet separated from
    the leader, until each rival trails it by this many standard errors of the per-view
    difference (a paired t statistic) or every training view is scored
    (`core.sequence.starts.race_starts`); 0 scores `start_views` views only. The renders a
    race takes beyond `start_views` come out of the refine stage (`FrameTracker.
    scoring_extra`), so the budget is unchanged. Replaying 40 tracked frames of two training
    seeds from every start (docs/method.md): four views chose a start that refined 0.5-0.75 dB
    below the best at frame 22 of both; all fourteen chose right there, and the race at 2
    chose as all fourteen did everywhere, scoring 19.4 views a frame instead of 11.6 (1.5:
    the same choices at 16.4; 1: four views' mistakes)."""
    lr_rotation: float = 2e-2
    """Adam rate of the node quaternions (decays exponentially to a tenth over the stage)."""
    lr_translation: float = 1e-2
    """Adam rate of the node translations, times the scene extent (decays like the rotations')."""
    arap: float = 0.02
    """Weight of the ARAP term (edge residuals relative to the mean edge length). Measured on
    the synthetic sequence (48x48, 5 tracked frames, held-out figure PSNR): 0.3 holds the graph
    too stiff for swinging limbs (14.1 dB), 0.05 20.7, 0.02 20.9, 0.01 20.5, 0 20.2."""
    quat_norm: float = 1.0
    """Weight of the node-quaternion unit-norm term."""
    coarse_sigma: float = 4.0
    """Deform stage: render and target are blurred by a Gaussian of this many pixels at the
    first step, shrinking linearly to none by the stage's middle (a wider basin for fast
    motion); 0 turns it off. On the synthetic sequence (48x48, frames 1-3, four seeds) 2 px
    left a group's third frame 1.0-3.3 dB below its second in three seeds, 4 px at most
    0.5 dB; 6 px no better than 4."""
    deform_views: int = 1
    """Deform stage: training views whose losses are averaged in each step (a gradient that
    agrees with several cameras instead of one at a time); each counts as a render of the
    frame's budget (`FrameTracker.renders`). At a fixed budget 1 view a step with the renders
    moved to the refine stage wins: 60 x 1 + 84 against 300 (21.85 dB) beat 42 x 2 + 60
    (about 0.3 dB lower on frames 1-3) and 57 x 2 + 30 (21.15 dB). Without that trade, 4
    gained 0.5 dB over 2 at 0.9 of a key frame's renders, and 1 lost 1.0 dB against 4 (at
    ARAP 0.05, 30 refine steps)."""
    deform_mask: float = 1.0
    """Deform stage: weight of L1 between the (blurred) appearance coverage and the capture's
    (blurred) mask, a silhouette term whose basin does not depend on the figure's colours
    (with ARAP 0.05: 15.8 -> 19.7 dB held-out on the synthetic sequence; 0 turns it off)."""
    deform_retries: int = 0
    """Deform rounds a frame may add when tracking falls behind (0: never). A round whose end
    loss (mean colour + silhouette L1 of its last sixth of steps, unblurred by then) is
    `retry_loss_ratio` times the previous frame's or more is followed by another from the next
    best start (`motion_candidates`), or from where it ended when no start is left, with fresh
    rates, blur and Adam moments; the round that ended lowest is kept. The signal is free (the
    losses were computed anyway); a group's second frame has no reference and never retries.
    Measured on the synthetic sequence (docs/method.md): good frames end at 0.8-1.16x their
    predecessor's loss, frames whose feet lost track at 1.24-1.93x; off by default because a
    retried quarter of the frames lifts a tracked frame past half a key frame's renders for
    +0.1 dB."""
    retry_loss_ratio: float = 1.2
    """The end-loss ratio to the previous frame's that starts a retry."""
    rekey_loss_ratio: float = 0.0
    """A tracked frame whose kept deform round ends at this ratio of the previous frame's end
    loss or more is made a key frame instead (the static stages from scratch, before any refine
    step): it starts a new group of pictures, and the frames after it deform from it. The
    deform stage it ran is still paid for (`renders` counts it). 0: never. The signal is the
    retry's (a group's second frame has no reference and is never re-keyed)."""
    refine_adapt: float = 3.0
    """Refine stage: its steps are the nominal (`refine_fraction`) times r ** refine_adapt,
    clipped to [`refine_min`, `refine_max`], where r is the kept deform round's end loss over
    the previous frame's (the retry's signal: a frame that tracked worse than its predecessor
    gets more refinement, one that tracked better fewer); a group's second frame follows a key
    frame, which has no deform loss, and compares with the median of the run's earlier tracked
    frames' (`core.sequence.budget.median_deform_loss`), or asks `refine_second` when there is none
    (the run's first group). Steps beyond the nominal are paid out of what earlier
    tracked frames of the run left unused, or borrowed against at most `refine_borrow` later
    ones, no more than they can pay back at `refine_min` (`core.sequence.budget.refine_credit`), so
    the run's tracked frames never refine more than the nominal on average: rate control at a
    constant budget, as a video encoder spends bits where the picture needs them (a frame
    re-keyed later pays nothing back). 0: fixed, the nominal everywhere. Measured on the
    synthetic sequence (four seeds, 88 in-group transitions): transitions dropping more than
    2 dB 17 with fixed steps, 10 spending savings only, 9 with the defaults (the drop into a
    group's second frame 1.7-2.3 dB -> 1.4-1.7); held-out PSNR 21.85 -> 22.05 dB."""
    refine_min: float = 0.85
    """Fewest refine steps, as a multiple of the nominal (`refine_adapt`; rounded up). 0.7
    saves more for the hard frames but did no better (8 transitions over 2 dB, largest drops
    2.2-4.2 dB against 2.4-3.5)."""
    refine_max: float = 2.0
    """Most refine steps, as a multiple of the nominal (`refine_adapt`)."""
    refine_borrow: int = 1
    """Most tracked frames ahead a run may borrow refine steps against (`refine_adapt`): its
    debt stays within what that many frames pay back at `refine_min`. 0: spend only what was
    saved. Measured on the synthetic sequence (four training seeds, `means_lr_scale` 3, second
    frames compared with the run's median): borrowing against 4 left the last frames of the
    run paying back at the floor, the hardest of them (frame 22) dropping 2.0-2.3 dB in three
    seeds; against 2, 1.9 dB on average (largest 2.4); against **1**, over eight seeds,
    1.98 dB (1.63-2.60), two transitions over 2 dB of 176, at the same held-out PSNR
    (22.90 dB). 1 and 2 are within the seeds' spread; with 1 the frames at the end of a run
    owe at most one frame's floor saving. (Before the position rate was raised, 4 beat 0 and
    unbounded borrowing: 9 transitions over 2 dB of 88 against 10.)"""
    refine_second: float = 2.0
    """Refine steps the run's first second frame asks (no tracked frame to compare with), as a
    multiple of the nominal (`refine_adapt`; within the credit and [`refine_min`,
    `refine_max`]): it follows a key frame trained from scratch, and with the nominal its drop
    from it was 1.7-2.3 dB in every seed. Later groups' second frames compare with the run's
    median tracked frame instead: on the synthetic sequence the second group's starts at the
    walk's easiest phase, and asking 2x there left frame 22, the hardest, at the floor."""
    temporal: bool = True
    """Refine stage: temporal L1 to the deformed values (off for the ablation)."""
    temporal_opacity_g: float = 0.01
    """Temporal weight of the geometry opacity (DESIGN.md section 5)."""
    temporal_means: float = 1.0
    """Temporal weight of the positions."""
    temporal_quats: float = 0.3
    """Temporal weight of the rotations."""
    temporal_normals: float = 0.5
    """Temporal weight of the normals."""
    anisotropy: float = 0.01
    """Weight of the anisotropy loss mean(max(s_max / s_min - r, 0)); 0 for the ablation."""
    anisotropy_ratio: float = 3.0
    """Largest scale ratio r the anisotropy loss leaves alone."""
    means_lr_scale: float = 3.0
    """Refine stage: position rate = this x the key frame's initial rate (no decay). Measured
    on the synthetic sequence (four training seeds, 24 frames): 0.1 (the default until
    2026-11-25) 22.07 dB held-out, 1 22.77, **3** 22.87, 10 22.68, 10 decaying to 1 over
    the stage 22.92; the largest in-group drop 2.74 -> 2.14 dB (mean of the seeds' largest)
    at 3. At 0.1 the refinement could move a Gaussian a few millimetres in 84 steps, less
    than the deformation's error on the fast limbs (a pixel is 4 cm at 48x48), so it
    sharpened colours over misplaced Gaussians."""
    densify_every: int = 0
    """Refine stage: steps between densifications (0: 4 per refine)."""
    max_growth: float = 0.02
    """Refine stage: densification adds at most this fraction of the frame's Gaussians."""
    bake_ao: bool = False
    """Refine stage: re-bake ambient occlusion of the deformed pose (visibility loss on). Off by
    default: the visibility attribute is carried over with its Gaussians, and a bake costs more
    than the rest of a small frame."""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, (int, float)) and not isinstance(value, bool) and value < 0:
                raise ValueError(f"sequence.{f.name}: expected >= 0, got {value}")
        if self.deform_views < 1:
            raise ValueError(f"sequence.deform_views: expected >= 1, got {self.deform_views}")
        if any(not 0 < a <= 2 for a in self.motion_candidates):
            raise ValueError(f"sequence.motion_candidates: expected dampings in (0, 2], got "
                             f"{self.motion_candidates}")
        if any(not -1 <= c <= 1 for c in self.second_order):
            raise ValueError(f"sequence.second_order: expected values of cos(w) in [-1, 1], got "
                             f"{self.second_order}")
        if self.retry_loss_ratio < 1:
            raise ValueError(f"sequence.retry_loss_ratio: expected >= 1 (a round no worse than "
                             f"the previous frame's never retries), got {self.retry_loss_ratio}")
        if 0 < self.rekey_loss_ratio < 1:
            raise ValueError(f"sequence.rekey_loss_ratio: expected 0 (never) or >= 1, got "
                             f"{self.rekey_loss_ratio}")
        if not 0 < self.refine_min <= 1 <= self.refine_max:
            raise ValueError(f"sequence.refine_min, refine_max: expected 0 < min <= 1 <= max, got "
                             f"{self.refine_min}, {self.refine_max}")
        if self.start_views < 1:
            raise ValueError(f"sequence.start_views: expected >= 1, got {self.start_views}")
        if self.num_nodes < 5:
            raise ValueError(f"sequence.num_nodes: expected >= 5 (4 blended + the 5th for d_max), "
                             f"got {self.num_nodes}")

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
