"""The training schedule as a pure function from step to stage (DESIGN.md section 5).

Paper preset, 30k iterations per key frame:
- stage 1 (0-7k): appearance only, SH degree 0, opacity_g tied to opacity_c, beta 0;
- stage 2 (7k-21k): geometry branch on (opacity_g its own parameter, normals initialised),
  normal-prior and depth-normal losses on, beta ramps 0 -> 0.7 (cosine) by the end of training;
- stage 3 (21k-30k): ambient occlusion baked at 21k, visibility loss on, SH degree raised to 3
  (one degree per 1000 steps, as 3DGS raises it).
Densification and opacity resets follow 3DGS (Kerbl et al. 2023, arguments/__init__.py):
densify every 100 steps from 500 to 15k, opacity reset (and pruning) every 3000 steps.
Other presets scale every step count by iterations / 30000.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Literal

__all__ = ["PRESETS", "Preset", "Schedule", "StagePlan", "plan", "schedule_for"]

Preset = Literal["paper", "fast", "test"]


@dataclass(frozen=True)
class Schedule:
    """Step counts and targets of the staged schedule (steps count from 0)."""

    iterations: int = 30_000
    """Total optimisation steps for a key frame."""
    stage2_start: int = 7_000
    """First step of stage 2 (geometry branch)."""
    stage3_start: int = 21_000
    """First step of stage 3 (AO baked, visibility loss); AO is baked at this step."""
    beta_max: float = 0.7
    """Beta reached at the last step by the cosine ramp that starts with stage 2."""
    sh_max_degree: int = 3
    """SH degree reached in stage 3."""
    sh_interval: int = 1_000
    """Steps per SH degree increase in stage 3 (3DGS oneupSHdegree every 1000)."""
    sh_start: int | None = None
    """Step at which the SH degree first rises (then one more every `sh_interval`); None: the
    start of stage 3 (DESIGN.md). A plain 3DGS (the appearance-only baseline) rises from
    `sh_interval` on, whatever the stage."""
    densify_from: int = 500
    """Densification runs at steps > densify_from (3DGS densify_from_iter)."""
    densify_until: int = 15_000
    """... and < densify_until (3DGS densify_until_iter); opacity resets stop here too."""
    densify_interval: int = 100
    """Steps between densifications (3DGS densification_interval)."""
    reset_interval: int = 3_000
    """Steps between opacity resets, each preceded by pruning (3DGS opacity_reset_interval)."""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "sh_start" and value is None:
                continue
            if f.name != "beta_max" and (not isinstance(value, int) or value < 0):
                raise ValueError(f"{f.name}: expected a non-negative integer, got {value!r}")
        if not 0 < self.stage2_start <= self.stage3_start <= self.iterations:
            raise ValueError(
                "stage2_start, stage3_start: expected 0 < stage2_start <= stage3_start <= "
                f"iterations, got {self.stage2_start}, {self.stage3_start}, {self.iterations}")
        if not 0.0 <= self.beta_max <= 1.0:
            raise ValueError(f"beta_max: expected a value in [0, 1], got {self.beta_max}")
        if self.sh_max_degree > 3:
            raise ValueError(f"sh_max_degree: expected 0..3, got {self.sh_max_degree}")
        for name in ("sh_interval", "densify_interval", "reset_interval"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")

    def scaled(self, iterations: int) -> Schedule:
        """The same plan for `iterations` steps: every step count scaled proportionally
        (intervals at least 1 step)."""
        if iterations < 3:
            raise ValueError(f"iterations: expected >= 3, got {iterations}")
        f = iterations / self.iterations
        counts = {name: max(1, round(getattr(self, name) * f)) for name in (
            "stage2_start", "stage3_start", "sh_interval", "densify_from", "densify_until",
            "densify_interval", "reset_interval")}
        counts["stage3_start"] = max(counts["stage3_start"], counts["stage2_start"])
        if self.sh_start is not None:
            counts["sh_start"] = round(self.sh_start * f)
        return replace(self, iterations=iterations, **counts)


PRESETS: dict[str, Schedule] = {
    "paper": Schedule(),
    "fast": Schedule().scaled(7_500),
    "test": Schedule().scaled(500),
}


def schedule_for(preset: str) -> Schedule:
    """The named preset's schedule."""
    if preset not in PRESETS:
        raise ValueError(f"preset: expected one of {sorted(PRESETS)}, got {preset!r}")
    return PRESETS[preset]


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
    photometric: bool
    """L1 + D-SSIM against the image (always on)."""
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


def plan(step: int, schedule: Schedule = Schedule()) -> StagePlan:
    """The plan at `step` (0 <= step < schedule.iterations). Pure: same input, same output."""
    if not isinstance(step, int) or not 0 <= step < schedule.iterations:
        raise ValueError(f"step: expected an integer in [0, {schedule.iterations}), got {step!r}")
    s = schedule
    stage: Literal[1, 2, 3] = 1 if step < s.stage2_start else (2 if step < s.stage3_start else 3)
    beta = 0.0
    if stage > 1:
        span = max(s.iterations - 1 - s.stage2_start, 1)
        t = min((step - s.stage2_start) / span, 1.0)
        beta = s.beta_max * 0.5 * (1.0 - math.cos(math.pi * t))
    sh = 0
    sh_start = s.stage3_start if s.sh_start is None else s.sh_start
    if step >= sh_start and (stage == 3 or s.sh_start is not None):
        sh = min(s.sh_max_degree, 1 + (step - sh_start) // s.sh_interval)
    in_window = s.densify_from < step < s.densify_until
    return StagePlan(
        step=step, stage=stage, beta=beta, sh_degree=sh, tie_opacity=stage == 1,
        geometry_branch=stage > 1, start_geometry=step == s.stage2_start and stage == 2,
        bake_ao=step == s.stage3_start and stage == 3, photometric=True,
        normal_prior=stage > 1, consistency=stage > 1, visibility=stage == 3,
        densify=in_window and step % s.densify_interval == 0,
        reset_opacity=0 < step < s.densify_until and step % s.reset_interval == 0,
    )
