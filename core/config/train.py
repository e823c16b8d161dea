"""How one frame is trained: the stage schedule, learning rates, densification, loss weights,
ambient-occlusion baking, and the named presets (docs/design.md, "Training")."""

from __future__ import annotations

import dataclasses
from dataclasses import field, replace
from typing import Annotated, Literal

from pydantic import Field

from core.config.base import DEVICE_PATTERN, MAX_STEPS, Device, Fraction, Positive, Steps, Weight, section
from core.config.rig import StereoConfig
from core.config.views import Masks

__all__ = ["AOConfig", "DEVICE_PATTERN", "DensifyConfig", "InitConfig", "LearningRates", "LossWeights",
           "METHODS", "Method", "PRESETS", "Preset", "Schedule", "TrainConfig", "method_defaults",
           "schedule_for", "train_config"]

Preset = Literal["paper", "fast", "test"]
Method = Literal["disentangled", "3dgs"]
METHODS: tuple[str, ...] = ("disentangled", "3dgs")
Rate = Annotated[float, Field(gt=0, le=1)]


@section
class Schedule:
    """Step counts and targets of the staged schedule (steps count from 0); densification and
    opacity resets follow 3DGS (Kerbl et al. 2023, arguments/__init__.py)."""

    iterations: Annotated[int, Field(ge=3, le=MAX_STEPS)] = 30_000
    """Total optimisation steps of a key frame."""
    stage2_start: Steps = 7_000
    """First step of stage 2 (geometry branch)."""
    stage3_start: Steps = 21_000
    """First step of stage 3 (AO baked, visibility loss, SH raised)."""
    beta_max: Fraction = 0.7
    """Beta reached at the last step by the cosine ramp that starts with stage 2."""
    sh_max_degree: Annotated[int, Field(ge=0, le=3)] = 3
    """SH degree reached in stage 3."""
    sh_interval: Annotated[int, Field(ge=1, le=MAX_STEPS)] = 1_000
    """Steps per SH degree increase (3DGS oneupSHdegree every 1000)."""
    sh_from: Literal["stage3", "start"] = "stage3"
    """When the SH degree starts to rise: `stage3`, with stage 3 (the paper: colour is view
    independent while the geometry branch learns, so view-dependent colour cannot explain its
    shading away); `start`, from step 0 as 3DGS raises it (a plain 3DGS always does)."""
    densify_from: Steps = 500
    """Densification runs at steps > densify_from (3DGS densify_from_iter)."""
    densify_until: Steps = 15_000
    """... and < densify_until (3DGS densify_until_iter); opacity resets stop here too."""
    densify_interval: Annotated[int, Field(ge=1, le=MAX_STEPS)] = 100
    """Steps between densifications (3DGS densification_interval); with `densify_epoch`, at
    least one epoch."""
    densify_epoch: bool = True
    """Densifications are at least an epoch apart: the trainer raises `densify_interval` to
    the number of training views (`for_views`), so a Gaussian's gradient statistic is a mean
    over every view that sees it, not over the handful drawn since the last one (a scaled
    schedule's interval: 4 steps of a 27-view key frame). False: `densify_interval` as given."""
    reset_interval: Annotated[int, Field(ge=1, le=MAX_STEPS)] = 3_000
    """Steps between opacity resets, each after pruning (3DGS opacity_reset_interval)."""

    def __post_init__(self) -> None:
        if not 0 < self.stage2_start <= self.stage3_start <= self.iterations:
            raise ValueError(
                "stage2_start, stage3_start: expected 0 < stage2_start <= stage3_start <= "
                f"iterations, got {self.stage2_start}, {self.stage3_start}, {self.iterations} "
                "(a preset's boundaries do not follow a new iterations: give them too)")

    def for_views(self, views: int) -> Schedule:
        """The schedule a key frame of `views` training views follows: with `densify_epoch`,
        `densify_interval` raised to `views`."""
        if views < 1:
            raise ValueError(f"views: expected >= 1, got {views}")
        if not self.densify_epoch or self.densify_interval >= views:
            return self
        return replace(self, densify_interval=views)

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


@section
class LearningRates:
    """Adam learning rates per parameter group: those of 3DGS (Kerbl et al. 2023,
    arguments/__init__.py OptimizationParams); the geometry branch's are ours."""

    means: Rate = 1.6e-4
    """Initial position rate, times the scene extent (3DGS position_lr_init)."""
    means_final: Rate = 1.6e-6
    """Position rate reached at `means_decay_steps`, log-linear decay (3DGS position_lr_final)."""
    means_decay_steps: Annotated[int, Field(ge=1, le=MAX_STEPS)] = 30_000
    """Steps of the exponential position decay (3DGS position_lr_max_steps)."""
    sh0: Rate = 2.5e-3
    """Degree-0 SH (3DGS feature_lr)."""
    shN: Rate = 2.5e-3 / 20
    """Higher SH degrees: feature_lr / 20 as in 3DGS gaussian_model.training_setup."""
    opacity: Rate = 5e-2
    """Both opacity logits (original 3DGS opacity_lr)."""
    scales: Rate = 5e-3
    """Log-scales (3DGS scaling_lr)."""
    quats: Rate = 1e-3
    """Quaternions (3DGS rotation_lr)."""
    normals: Rate = 1e-2
    """Unnormalized normals: the paper's 0.01 (1e-3 until 2026-11-27: on the synthetic figure
    with priors, fast preset, 0.01 gave normal cosine 0.9655 against 0.9651 and held-out PSNR
    within 0.06 dB, docs/design.md 5.1)."""
    visibility: Rate = 2.5e-3
    """Visibility logit (ours; the colour rate)."""

    def for_param(self, name: str, extent: float) -> float:
        """The initial rate of parameter group `name` in a scene of `extent`."""
        if name == "means":
            return self.means * extent
        if name in ("opacity_c", "opacity_g"):
            return self.opacity
        return float(getattr(self, name))


@section
class DensifyConfig:
    """Thresholds and factors of the densification strategy (`core.strategy`)."""

    gradient: Literal["absolute", "mean"] = "absolute"
    """The screen-space gradient statistic: `absolute`, AbsGS (Ye et al. 2024: per view the
    sum over pixels of |dL/d mean2d|, per branch); `mean`, 3DGS (per view |dL/d mean2d|, both
    branches together; gsplat DefaultStrategy absgrad=False). Either is averaged over the
    views that drew the Gaussian and measured in NDC units."""
    grad_threshold_c: Positive = 0.0008
    """Densify above this statistic in the appearance branch (AbsGS / gsplat absgrad default
    0.0008; 3DGS densify_grad_threshold 0.0002 with `gradient` mean)."""
    grad_threshold_g: Positive = 0.0008
    """... in the geometry branch (unused with `gradient` mean)."""
    clone_scale: Positive = 0.01
    """Clone when the largest scale <= clone_scale x extent, else split (3DGS percent_dense)."""
    split_factor: Annotated[float, Field(ge=1, le=100)] = 1.6
    """Split samples get scales / split_factor (3DGS: 0.8 x 2 samples)."""
    revised_opacity: bool = True
    """Both Gaussians of a clone or split take opacity 1 - sqrt(1 - o) in a branch that passed
    (Bulo et al. 2024), so together they cover like the original; off: both keep o (3DGS)."""
    new_branch_opacity: Annotated[float, Field(gt=0, lt=1)] = 0.005
    """Opacity of the copy in a branch that did not pass its threshold."""
    transparent: Fraction = 0.005
    """Below this opacity in both branches a Gaussian is pruned (3DGS min_opacity)."""
    relocate: bool = False
    """Transparent Gaussians are moved, not pruned: at each densification those under
    `transparent` in both branches take the place of copies of live ones drawn by appearance
    opacity, and each drawn one and its copies share its cover (3DGS-MCMC's relocation,
    Kheradmand et al. 2024, Eq. 9). Under a cap the slots pruning frees are then refilled where
    the picture is, not by the next densification's gradients."""
    prune_at: Literal["reset", "densify"] = "reset"
    """When transparent Gaussians are pruned: at each opacity reset, or at each densification
    (3DGS densify_and_prune, gsplat DefaultStrategy)."""
    rho: Fraction = 0.1
    """Initial fraction pruned by lowest contribution at a reset (0.25 for ActorsHQ-like;
    0: none, as in 3DGS)."""
    rho_decay: Fraction = 0.75
    """rho is multiplied by this after each reset."""
    reset_value: Annotated[float, Field(gt=0, lt=1)] = 0.01
    """Opacity reset: o = min(o, reset_value) (3DGS)."""
    reset_opacity: bool = True
    """Reset opacities at each reset step (3DGS). Off: the reset steps still prune and count as
    resets (the too-big pruning starts after the first), but opacities are left alone, as in
    gsplat 1.5.3's `DefaultStrategy`, whose reset condition `step % reset_every == 0 & step > 0`
    never holds (fixed by gsplat pull request 776, after that release)."""
    max_gaussians: Annotated[int, Field(ge=1, le=50_000_000)] | None = None
    """Stop growing beyond this many Gaussians (highest gradients densify first); None: no cap."""
    prune_scale: Positive | None = 0.1
    """After the first reset, drop Gaussians whose largest scale exceeds this x the scene extent
    (3DGS `0.1 * cameras_extent`); None keeps them."""


@section
class LossWeights:
    """Weight of each loss term (docs/design.md, "Losses"); 0 turns a term off."""

    dssim: Fraction = 0.2
    """Share of D-SSIM in the photometric loss; L1 gets 1 - dssim."""
    normal_l1: Weight = 0.2
    """L1 between rendered normals and the prior."""
    normal_smooth: Weight = 0.05
    """Edge-aware smoothness of rendered normals."""
    normal_confidence: Literal["absolute", "by_source", "per_view"] = "by_source"
    """How a prior's confidence (the rig's priors, `core.rig`) weighs it: `per_view`, it ranks
    a view's pixels against each other (a view whose priors are all uncertain pulls as hard as
    a sure one); `absolute`, a pixel of confidence c pulls c times as hard as a sure one (the
    visual hull's 0.5 half as hard as the capture's normals/); `by_source`, stereo's
    confidences (a ramp on the plane fit's residual) per view and the hull's (a guess every
    view shares) absolutely: per view's on captures without mattes (the Panoptic twin, where
    absolute lost 0.3 dB), absolute's on the synthetic figure (+0.37 dB over per view, three
    seeds), level with per view on the masked fox (three seeds; docs/benchmarks.md)."""
    consistency: Weight = 0.01
    """Depth-normal consistency."""
    visibility_l1: Weight = 0.1
    """L1 between rendered visibility and the baked AO maps."""
    visibility_smooth: Weight = 0.01
    """Smoothness of rendered visibility."""
    geometry_mask: Weight = 1.0
    """L1 between the geometry coverage and the capture's mask (ours: keeps geometry-only
    Gaussians out of the background)."""
    opacity_l1: Weight = 0.0
    """Mean opacity of the Gaussians (both opacities once the geometry branch has its own), as
    3DGS-MCMC (Kheradmand et al. 2024) regularizes it (0.01 there): a Gaussian that does not
    earn its opacity fades and is pruned. 0: off (the paper has none)."""
    scale_l1: Weight = 0.0
    """Mean scale of the Gaussians over the scene extent (3DGS-MCMC: 0.01 on the mean scale in
    scene units; ours is over the extent, so one weight suits every capture's units). 0: off."""


@section
class AOConfig:
    """How ambient occlusion is baked (`core.ao`)."""

    n_dirs: Annotated[int, Field(ge=1, le=1024)] = 64
    """Rays per point, over the Fibonacci hemisphere about its normal."""
    scale: Annotated[float, Field(gt=0, le=1)] = 0.25
    """Resolution of the traced maps relative to the training views."""
    max_map_pixels: Annotated[int, Field(ge=256, le=2**24)] | None = 65_536
    """At most this many pixels in a view's traced map: larger views trace at a lower scale
    (AO is smooth; the joint bilateral filter restores full resolution along the normals).
    None: `scale` alone."""
    min_alpha: Annotated[float, Field(gt=0, lt=1)] = 0.5
    """Pixels whose geometry coverage is below this are background (AO 1)."""
    offset_pixels: Annotated[float, Field(ge=0, le=100)] = 0.5
    """Rays start this many full-resolution pixel footprints above the rendered surface, clear
    of the thin Gaussians that make it."""
    sigma_color: Annotated[float, Field(gt=0, le=10)] = 0.2
    """Joint bilateral filter: range sigma on the normal guide (components in -1..1)."""
    sigma_space: Annotated[float, Field(gt=0, le=64)] = 2.0
    """Joint bilateral filter: spatial sigma in full-resolution pixels."""


@section
class InitConfig:
    """Where a key frame's initial Gaussians come from (`core.seeding.seed_points`)."""

    source: Literal["auto", "points", "stereo", "triangulate", "random"] = "auto"
    """auto: the capture's points.ply, else dense points fused from the views' stereo depth,
    else points triangulated from the known poses, else (with a warning) random points;
    `points`, `stereo`, `triangulate` or `random` ask for one alone."""
    background: Annotated[float, Field(ge=0, le=10)] = 0.1
    """Views without masks: points on a far shell along the cameras' pixel rays, this fraction
    of the other seeds (0: none), for the distant background that triangulation misses."""
    stereo: StereoConfig = field(default_factory=StereoConfig)
    """How the views' depth is matched and fused (dense seeds and the rig's normal priors)."""


Color = Annotated[float, Field(ge=0, le=1)]


@section
class TrainConfig:
    """Everything that decides how one key frame is reconstructed."""

    method: Method = "disentangled"
    """`disentangled`: the method (docs/design.md 5: two opacities, the staged schedule, the
    geometry branch, AO). `3dgs`: a plain 3D Gaussian Splatting (Kerbl et al. 2023), the
    comparison baseline: one opacity, no geometry branch, the SH degree raised every
    `sh_interval` steps from the start, the photometric loss alone; with it a run's other
    settings default to 3DGS's (`method_defaults`)."""
    schedule: Schedule = field(default_factory=Schedule)
    """Stage boundaries, beta ramp, densification and reset timing."""
    rates: LearningRates = field(default_factory=LearningRates)
    """Adam learning rates per parameter group."""
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    """Densification and pruning thresholds."""
    losses: LossWeights = field(default_factory=LossWeights)
    """Loss weights."""
    ao: AOConfig = field(default_factory=AOConfig)
    """Ambient-occlusion baking."""
    init_points: Annotated[int, Field(ge=1, le=10_000_000)] = 100_000
    """Random initial points where neither the capture nor triangulation gives any; with masks,
    the visual hull is filled with random points up to this many seeds."""
    init: InitConfig = field(default_factory=InitConfig)
    """Where the initial points come from (the capture's points.ply, triangulation, random)."""
    eps2d: Annotated[float, Field(ge=0, le=10)] = 0.1
    """Screen-space blur of the Mip-Splatting 2D filter."""
    antialiased: bool = True
    """Apply the Mip-Splatting opacity compensation."""
    near: Positive | None = None
    """Near plane of every render, training and evaluation alike (camera depth, scene units):
    nothing closer is drawn. None: a fifth of the rig's median camera distance to the point
    its cameras look at, at most twice their spread (`core.data.layout.near_plane`), resolved
    against the capture with the run, so RUN/config.json records the number."""
    background: tuple[Color, Color, Color] = (0.0, 0.0, 0.0)
    """Colour behind the Gaussians; masked-out target pixels take it too."""
    masks: Masks = "capture"
    """How the capture's masks are used: `matte`, they cut the subject out of each picture and
    only it is reconstructed (on `background`); `subject`, the whole picture is reconstructed
    and the masks only mark the subject (what tracked frames move, what a subject export
    keeps); `capture`, what the capture says it has (capture.json `masks`, default matte)."""
    random_background: bool = True
    """Views with a mask train in front of a new random colour each step (render and target
    alike), so coverage must match the mask (3DGS --random_background)."""
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    """Seeds initial points, view order and split samples."""
    bake_ao: bool = True
    """Bake ambient occlusion at stage 3's first step; off: the visibility loss stays off."""
    device: Device = "auto"
    """Where training runs: auto (CUDA when usable, else the CPU; $DGS_DEVICE when set), cpu,
    cuda or cuda:N. RUN/config.json records the device it resolved to."""

    def to_dict(self) -> dict:
        """The fully resolved configuration as JSON-compatible data."""
        return dataclasses.asdict(self)

    def stretched(self, factor: float) -> TrainConfig:
        """This configuration with `factor` times the steps: the schedule scaled, the position
        decay over the same share of the run."""
        if factor == 1.0:
            return self
        iterations = max(3, round(self.schedule.iterations * factor))
        decay = max(1, round(self.rates.means_decay_steps * factor))
        return replace(self, schedule=self.schedule.scaled(iterations),
                       rates=replace(self.rates, means_decay_steps=decay))


def method_defaults(config: TrainConfig, method: str) -> TrainConfig:
    """`config` with `method`'s defaults laid on it. For `3dgs` those of the reference 3DGS
    (arguments/__init__.py, gaussian_model.densify_and_prune) and gsplat's DefaultStrategy:
    the mean screen gradient above 0.0002, clones and splits keeping their opacity,
    transparent Gaussians pruned at every densification, no pruning by contribution, the
    classic rasterization (2D blur 0.3, no antialiasing compensation), no AO bake."""
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if method == "disentangled":
        return replace(config, method="disentangled")
    densify = replace(config.densify, gradient="mean", grad_threshold_c=0.0002,
                      revised_opacity=False, prune_at="densify", rho=0.0)
    return replace(config, method="3dgs", densify=densify, eps2d=0.3, antialiased=False,
                   bake_ao=False)


def train_config(preset: str, method: str = "disentangled") -> TrainConfig:
    """Named presets: `paper` (30k steps), `fast` (7.5k) and `test` (500, tiny captures), for
    `method` (`method_defaults`)."""
    schedule = schedule_for(preset)
    rates = replace(LearningRates(), means_decay_steps=schedule.iterations)
    if preset == "paper":
        config = TrainConfig(schedule=schedule)
    elif preset == "fast":
        config = TrainConfig(schedule=schedule, init_points=50_000, rates=rates)
    else:
        config = TrainConfig(schedule=schedule, init_points=1_000, rates=rates,
                             densify=replace(DensifyConfig(), max_gaussians=4_000))
    return method_defaults(config, method)
