"""The training schedule as a pure function from step to stage (docs/design.md section 5).

Paper preset, 30k iterations per key frame:
- stage 1 (0-7k): appearance only, SH degree 0, opacity_g tied to opacity_c, beta 0;
- stage 2 (7k-21k): geometry branch on (opacity_g its own parameter, normals initialised),
  normal-prior and depth-normal losses on, beta ramps 0 -> 0.7 (cosine) by the end of training;
- stage 3 (21k-30k): ambient occlusion baked at 21k, visibility loss on, SH degree raised to 3
  (one degree per 1000 steps, as 3DGS raises it; `Schedule.sh_from` "start" raises it from step
  0 instead).
Densification and opacity resets follow 3DGS (Kerbl et al. 2023, arguments/__init__.py):
densify every 100 steps from 500 to 15k, opacity reset (and pruning) every 3000 steps.
Other presets scale every step count by iterations / 30000.

A plain 3DGS (`TrainConfig.method` "3dgs") stays in stage 1 throughout and raises the SH degree
every `sh_interval` steps from the start (3DGS oneupSHdegree every 1000 iterations).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from core.config import METHODS, Method, Schedule

__all__ = ["StagePlan", "plan"]


@dataclass(frozen=True)
class StagePlan:
    """What the trainer does at one step."""

    step: int
    """The step this plan is for."""
    stage: Literal[1, 2, 3]
    """1 appearance only, 2 geometry branch, 3 AO and full SH."""
    beta: float
    """Opacity mixing factor passed to the rasterizer."""
    sh_degree: int
    """SH degree used for colour."""
    tie_opacity: bool
    """Render with opacity_g = opacity_c (stage 1)."""
    geometry_branch: bool
    """Render the geometry features (normals, visibility)."""
    start_geometry: bool
    """First step of stage 2: untie opacity_g and initialise normals before rendering."""
    bake_ao: bool
    """First step of stage 3: bake ambient occlusion before rendering."""
    normal_prior: bool
    """Normal-prior loss (when the view has a prior)."""
    consistency: bool
    """Depth-normal consistency loss."""
    visibility: bool
    """Visibility loss against the baked AO maps (when they exist)."""
    densify: bool
    """Run the densification strategy after this step's backward pass."""
    reset_opacity: bool
    """Prune, then reset opacities, after this step's backward pass."""


def plan(step: int, schedule: Schedule = Schedule(), method: Method = "disentangled") -> StagePlan:
    """The plan at `step` (0 <= step < schedule.iterations) of `method`. Pure: same input,
    same output."""
    if not isinstance(step, int) or not 0 <= step < schedule.iterations:
        raise ValueError(f"step: expected an integer in [0, {schedule.iterations}), got {step!r}")
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    s = schedule
    stage: Literal[1, 2, 3] = 1 if step < s.stage2_start else (2 if step < s.stage3_start else 3)
    if method == "3dgs":
        stage = 1
    beta = 0.0
    if stage > 1:
        span = max(s.iterations - 1 - s.stage2_start, 1)
        t = min((step - s.stage2_start) / span, 1.0)
        beta = s.beta_max * 0.5 * (1.0 - math.cos(math.pi * t))
    sh = 0
    if method == "3dgs" or s.sh_from == "start":
        sh = min(s.sh_max_degree, step // s.sh_interval)
    elif stage == 3:
        sh = min(s.sh_max_degree, 1 + (step - s.stage3_start) // s.sh_interval)
    in_window = s.densify_from < step < s.densify_until
    return StagePlan(
        step=step, stage=stage, beta=beta, sh_degree=sh, tie_opacity=stage == 1,
        geometry_branch=stage > 1, start_geometry=step == s.stage2_start and stage == 2,
        bake_ao=step == s.stage3_start and stage == 3,
        normal_prior=stage > 1, consistency=stage > 1, visibility=stage == 3,
        densify=in_window and step % s.densify_interval == 0,
        reset_opacity=0 < step < s.densify_until and step % s.reset_interval == 0,
    )
