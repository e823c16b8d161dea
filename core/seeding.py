"""Initial points of a key frame (`seed_points`), in order of preference:

1. the capture's own point cloud (``points.ply``: COLMAP points3D, a nerfstudio PLY, ...);
2. dense points: every view's stereo depth fused across the calibrated views (`core.rig`),
   sampled to the seed budget with their colours;
3. sparse points triangulated from the known poses (`core.triangulation`);
4. random points in the cameras' common view, only when none gives any (with a warning).
Where the views have mattes, every seed must land on the foreground of every view it projects
into (a visual hull), and the hull is topped up with random points inside it up to
`TrainConfig.init_points`. Where they have none, a far shell of points along the cameras' pixel
rays stands for the background no feature reaches. Where masks mark a subject inside a scene
(`subjects`), the seeds outside the subject's hull are the static scene: a later key frame keeps
them (`static`) and seeds only the subject from its own frame.
Also the scene extent that scales the position learning rate and densification.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from core.config import InitConfig
from core.data.capture import Camera
from core.data.layout import common_radius, look_at_center
from core.data.points import PointCloud
from core.rig.geometry import RigGeometry
from core.triangulation import in_visual_hull, pixel_indices

__all__ = ["ENCLOSURE_DEPTH", "ENCLOSURE_SPREAD", "SUBJECT_DILATE", "Seed", "encloses",
           "look_at_center", "sample_points", "scene_extent", "seed_budget", "seed_points",
           "shell_points", "subject_hull"]

log = logging.getLogger("dgs.seeding")

# Fewer seeds than this from a capture or triangulation are no scene: fall back.
MIN_POINTS = 32


CLEARANCE = 0.07
"""Seeds closer to a camera centre than this fraction of its distance to the cameras' look-at
centre are dropped: a camera's lens is there, and on a dome whose wall holds the cameras a
fused point of the wall just in front of a held-out camera grows into a Gaussian over its whole
view (the Panoptic twin's test camera 0: 15.3 dB with two such seeds)."""

SUBJECT_DILATE = 4
"""Pixels the subject masks grow by before they restrict a later key frame's depth (its
outline is matched too)."""


@dataclass
class Seed:
    """Initial points (N, 3) and colours (N, 3) in 0..1, with what they came from."""

    points: torch.Tensor
    colors: torch.Tensor
    note: str
    """One line for the run's notes: the source and the counts."""
    parts: list[tuple[str, PointCloud]] = field(default_factory=list)
    """The seeds by source, in order (fused, triangulated, capture, random, background,
    static, subject): what the seeds picture colours them by."""
    static: PointCloud | None = None
    """With subject masks: the seeds outside the subject's hull (the static scene a later key
    frame keeps); None without."""


ENCLOSURE_SPREAD = 0.5
"""`encloses`: largest norm of the mean camera direction of cameras around a scene."""
ENCLOSURE_DEPTH = 1.25
"""`encloses`: largest ratio of the farthest camera's distance to the nearest's."""


def scene_extent(cameras: Sequence[Camera]) -> float:
    """1.1 x the largest distance of a camera centre from their mean (3DGS getNerfppNorm)."""
    if not cameras:
        raise ValueError("cameras: expected at least one camera")
    centers = np.stack([c.center for c in cameras])
    radius = float(np.linalg.norm(centers - centers.mean(axis=0), axis=1).max())
    return 1.1 * radius if radius > 0 else 1.0


def sample_points(cameras: Sequence[Camera], n: int, *, images: Sequence[np.ndarray] | None = None,
                  masks: Sequence[np.ndarray | None] | None = None, seed: int = 0,
                  max_rounds: int = 50) -> tuple[torch.Tensor, torch.Tensor]:
    """Up to `n` points (n, 3) and colours (n, 3) inside the cube about the cameras' look-at centre
    that every camera sees; with masks (H, W, 1) a point must land on foreground (> 0.5) in every
    camera. Colours: mean of `images` (H, W, 3) at the projections (grey without images)."""
    if n < 1:
        raise ValueError(f"n: expected >= 1, got {n}")
    if images is not None and len(images) != len(cameras):
        raise ValueError(f"images: expected {len(cameras)} images, got {len(images)}")
    if masks is not None and len(masks) != len(cameras):
        raise ValueError(f"masks: expected {len(cameras)} masks, got {len(masks)}")
    rng = np.random.default_rng(seed)
    center = look_at_center(cameras)
    r = common_radius(cameras, center)
    kept: list[np.ndarray] = []
    total = 0
    for _ in range(max_rounds):
        pts = center + rng.uniform(-r, r, size=(4 * n, 3))
        ok = np.ones(len(pts), dtype=bool)
        for cam in cameras:
            uv, z = cam.project(pts)
            ok &= pixel_indices(uv, cam.width, cam.height, z)[2]
        if masks is not None:
            ok &= in_visual_hull(pts, cameras, masks)
        kept.append(pts[ok])
        total += int(ok.sum())
        if total >= n:
            break
    pts = np.concatenate(kept)[:n]
    if len(pts) == 0:
        raise ValueError("masks: no point lands on foreground in every camera; check the masks")
    return torch.from_numpy(pts).float(), torch.from_numpy(_colours(cameras, pts, images)).float()


def _colours(cameras: Sequence[Camera], pts: np.ndarray,
             images: Sequence[np.ndarray] | None) -> np.ndarray:
    if images is None:
        return np.full((len(pts), 3), 0.5)
    acc = np.zeros((len(pts), 3))
    for cam, img in zip(cameras, images):
        u, v, _ = pixel_indices(cam.project(pts)[0], cam.width, cam.height)
        acc += img[v, u, :3]
    return np.clip(acc / len(cameras), 0.0, 1.0)


def shell_points(cameras: Sequence[Camera], images: Sequence[np.ndarray], n: int,
                 center: np.ndarray, radius: float, seed: int = 0) -> PointCloud:
    """`n` points where random pixel rays of random cameras leave the sphere (`center`,
    `radius`) that holds them, coloured by their pixels."""
    rng = np.random.default_rng(seed)
    which = rng.integers(0, len(cameras), size=n)
    pts, cols = np.zeros((n, 3)), np.zeros((n, 3))
    for i in np.unique(which):
        sel = np.flatnonzero(which == i)
        cam, img = cameras[i], images[i]
        u = rng.uniform(0, cam.width, size=len(sel))
        v = rng.uniform(0, cam.height, size=len(sel))
        d = np.linalg.solve(cam.K, np.stack([u, v, np.ones_like(u)]))  # camera rays
        d = (cam.R.T @ d).T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = cam.center - center
        b = d @ o
        t = -b + np.sqrt(np.maximum(b * b - (o @ o - radius * radius), 0.0))  # far root
        pts[sel] = cam.center + t[:, None] * d
        px, py, _ = pixel_indices(np.stack([u, v], axis=1), cam.width, cam.height)
        cols[sel] = img[py, px, :3]
    return PointCloud(pts, np.clip(cols, 0, 1).astype(np.float32))


def seed_budget(n_random: int, max_gaussians: int | None) -> int:
    """Dense seeds to sample: `init_points`, at most half the densification cap (the other half
    is densification's room)."""
    return n_random if max_gaussians is None else max(1, min(n_random, max_gaussians // 2))


def _sample(cloud: PointCloud, n: int, seed: int) -> PointCloud:
    """`n` of the cloud's points drawn without replacement (all when it has no more)."""
    if len(cloud) <= n:
        return cloud
    keep = np.random.default_rng(seed).choice(len(cloud), size=n, replace=False)
    return cloud.subset(np.sort(keep))


HULL_SHARE = 0.5
"""With mattes, the share of the seed budget left to random points in the visual hull: stereo
misses thin or flat parts (a limb at 64 pixels) that the masks still show, and a part no seed
reaches is not grown in a short schedule."""


def _dense(rig: RigGeometry, masks: Sequence[np.ndarray | None], budget: int,
           seed: int) -> tuple[PointCloud, str]:
    fused = rig.fused()
    inside = fused.cloud.subset(in_visual_hull(fused.cloud.points, rig.cameras, masks))
    if any(m is not None for m in masks):
        budget = max(1, round(budget * (1 - HULL_SHARE)))
    cloud = _sample(inside, budget, seed)
    return cloud, (f"{len(cloud)} of {len(inside)} points fused from the views' stereo depth "
                   f"({len(fused.cameras)} views, {fused.cameras[0].width}x"
                   f"{fused.cameras[0].height})")


def _source_cloud(rig: RigGeometry, config: InitConfig, capture_points: PointCloud | None,
                  budget: int, seed: int) -> tuple[PointCloud | None, str, str]:
    """The capture's points (carved by the mattes), dense fused points or triangulated ones,
    with a note and the source's name; None when none gives MIN_POINTS (ValueError when the
    source asked for gives none)."""
    cameras, masks = rig.cameras, rig.masks
    cloud, what, name = None, "", ""
    if config.source in ("auto", "points") and capture_points is not None:
        cloud = capture_points.subset(in_visual_hull(capture_points.points, cameras, masks))
        what, name = f"{len(cloud)} of the capture's {len(capture_points)} points", "capture"
    elif config.source == "points":
        raise ValueError("init.source: 'points' needs a points.ply in the capture; use auto")
    if config.source in ("auto", "stereo") and (cloud is None or len(cloud) < MIN_POINTS):
        cloud, what = _dense(rig, masks, budget, seed)
        name = "fused"
    if config.source in ("auto", "triangulate") and (cloud is None or len(cloud) < MIN_POINTS):
        cloud, stats = rig.sparse()
        what = (f"{stats.points} points triangulated from the known poses ({stats.features} "
                f"features, {stats.matches} matches in {stats.pairs} camera pairs)")
        name = "triangulated"
    found = 0 if cloud is None else len(cloud)
    if config.source == "random" or found >= MIN_POINTS:
        return cloud, what, name
    if config.source != "auto":
        raise ValueError(f"init.source: {config.source!r} gave {found} points; use auto "
                         "(random points as the last resort)")
    return None, what, name


def subject_hull(points: np.ndarray, cameras: Sequence[Camera],
                 subjects: Sequence[np.ndarray | None], share: float = 0.5) -> np.ndarray:
    """(N,) whether each point is the subject's: it lands on the subject mask (H, W, 1) > 0.5
    in at least `share` of the views with a mask that it projects into."""
    hits = np.zeros(len(points))
    seen = np.zeros(len(points))
    for cam, mask in zip(cameras, subjects):
        if mask is None:
            continue
        uv, z = cam.project(points)
        u, v, inside = pixel_indices(uv, cam.width, cam.height, z)
        seen += inside
        hits += inside & (mask[v, u, 0] > 0.5)
    return (seen > 0) & (hits >= share * np.maximum(seen, 1))


def _grown(masks: Sequence[np.ndarray | None], pixels: int) -> list[np.ndarray | None]:
    kernel = np.ones((2 * pixels + 1, 2 * pixels + 1), np.uint8)
    return [None if m is None else cv2.dilate((m[..., 0] > 0.5).astype(np.uint8),
                                              kernel)[..., None].astype(np.float32)
            for m in masks]


def encloses(cameras: Sequence[Camera], center: np.ndarray) -> bool:
    """Whether the cameras are mounted around `center` on one enclosure (a studio dome): they
    surround it (the mean of the unit directions from it to them is under
    `ENCLOSURE_SPREAD`) at nearly one distance (within `ENCLOSURE_DEPTH` of each other). The
    Panoptic dome: 0.33 and 1.04; the fox (hand-held, one side): 0.81 and 1.67."""
    d = np.stack([c.center for c in cameras]) - center
    r = np.linalg.norm(d, axis=1)
    if len(cameras) < 4 or r.min() <= 0:
        return False
    spread = float(np.linalg.norm((d / r[:, None]).mean(axis=0)))
    return spread < ENCLOSURE_SPREAD and float(r.max() / r.min()) < ENCLOSURE_DEPTH


def _background(cameras: Sequence[Camera], images: Sequence[np.ndarray],
                masks: Sequence[np.ndarray | None], cloud: PointCloud, fraction: float,
                seed: int, n_random: int) -> tuple[PointCloud, str]:
    """The far shell of the views without masks: twice as far from the look-at centre as the
    farther of the cameras and the seeds (99th percentile), `fraction` of the seeds. Inside an
    enclosure (`encloses`) the background is the enclosure the cameras are mounted on, which
    fills most of every view: the shell is at the cameras' distance, and it has at least
    `fraction` x `n_random` points."""
    center = look_at_center(cameras)
    cams = np.linalg.norm(np.stack([c.center for c in cameras]) - center, axis=1)
    n = max(1, round(fraction * len(cloud)))
    if encloses(cameras, center):
        radius, what = float(cams.mean()), "the enclosure: a shell"
        n = max(n, round(fraction * n_random))
    else:
        reach = max(cams.max(), float(np.percentile(np.linalg.norm(cloud.points - center,
                                                                   axis=1), 99)))
        radius, what = 2.0 * reach, "a shell"
    unmasked = [i for i, m in enumerate(masks) if m is None]
    shell = shell_points([cameras[i] for i in unmasked], [images[i] for i in unmasked], n,
                         center, radius, seed)
    return shell, f"{n} background points on {what} of radius {radius:.3g}"


def seed_points(cameras: Sequence[Camera], images: Sequence[np.ndarray],
                masks: Sequence[np.ndarray | None], config: InitConfig, *, n_random: int,
                capture_points: PointCloud | None = None, seed: int = 0,
                rig: RigGeometry | None = None, max_gaussians: int | None = None,
                subjects: Sequence[np.ndarray | None] | None = None,
                static: PointCloud | None = None, threads: int = 0,
                clear_of: Sequence[Camera] = ()) -> Seed:
    """The initial points of a key frame from its training views (cameras served at the
    images' resolution, images (H, W, 3) and mattes (H, W, 1) or None), following the module's
    order; `n_random` is TrainConfig.init_points, `max_gaussians` the densification cap (dense
    seeds: `seed_budget`). `rig` is the views' `RigGeometry` (made here when None);
    `subjects` (H, W, 1) or None mark a subject inside a scene; `static` is the static scene
    kept from the run's first key frame (then only the subject is seeded from these views);
    no seed is left within `CLEARANCE` of these cameras or of `clear_of` (the capture's other
    cameras: their lenses are there too). ValueError when the source asked for explicitly has
    nothing to give."""
    out = _seed(cameras, images, masks, config, n_random, capture_points, seed, rig,
                max_gaussians, subjects, static, threads)
    return _cleared(out, [*cameras, *clear_of])


def _cleared(out: Seed, cameras: Sequence[Camera]) -> Seed:
    """`out` without the seeds within `CLEARANCE` of a camera (module constant)."""
    centers = np.stack([c.center for c in cameras])
    reach = CLEARANCE * np.linalg.norm(centers - look_at_center(cameras), axis=1)

    def keep(points: np.ndarray) -> np.ndarray:
        ok = np.ones(len(points), bool)
        for c, r in zip(centers, reach):
            ok &= np.linalg.norm(points - c, axis=1) > r
        return ok

    parts = [(name, cloud.subset(keep(cloud.points))) for name, cloud in out.parts]
    cleared = _joined(parts, out.note) if parts else out
    dropped = len(out.points) - len(cleared.points)
    if dropped:
        cleared.note = f"{out.note} ({dropped} within {CLEARANCE:g} of a camera's distance " \
            "dropped)"
    if out.static is not None:
        cleared.static = out.static.subset(keep(out.static.points))
    return cleared


def _seed(cameras, images, masks, config, n_random, capture_points, seed, rig, max_gaussians,
          subjects, static, threads) -> Seed:
    budget = seed_budget(n_random, max_gaussians)
    if static is not None and subjects is not None and any(m is not None for m in subjects):
        return _subject_seed(cameras, images, masks, config, subjects, static, budget, seed,
                             threads)
    if rig is None:
        rig = RigGeometry(cameras, images, masks, config.stereo, threads=threads)
    cloud, what, name = _source_cloud(rig, config, capture_points, budget, seed)
    masked = any(m is not None for m in masks)
    parts, notes = ([(name, cloud)], [what]) if cloud is not None else ([], [])
    if cloud is None or masked:  # random points, carved by the masks: all, or the hull's fill
        n = n_random if cloud is None else max(0, n_random - len(cloud))
        try:
            pts, cols = sample_points(cameras, n, images=images, masks=masks, seed=seed) \
                if n else (torch.zeros(0, 3), torch.zeros(0, 3))
        except ValueError:
            if cloud is None:  # nothing at all to start from
                raise
            pts, cols = torch.zeros(0, 3), torch.zeros(0, 3)  # the hull is too thin to sample
        if len(pts):
            parts.append(("random", PointCloud(pts.double().numpy(), cols.numpy())))
            where = "in the visual hull" if masked else "in the cameras' common view"
            fallback = ""
            if cloud is None and config.source != "random":
                fallback = f" (a fallback: {what})"
                log.warning("seeding %d random points %s, the last resort: %s", len(pts), where,
                            what)
            notes.append(f"{len(pts)} random points {where}{fallback}")
    if not all(m is not None for m in masks) and config.background > 0 and cloud is not None:
        shell, note = _background(cameras, images, masks, cloud, config.background, seed,
                                  n_random)
        parts.append(("background", shell))
        notes.append(note)
    out = _joined(parts, "seeded with " + " + ".join(notes))
    if subjects is not None and any(m is not None for m in subjects):
        pts = out.points.double().numpy()
        out.static = PointCloud(pts, out.colors.numpy()).subset(
            ~subject_hull(pts, cameras, subjects))
    return out


def _subject_seed(cameras: Sequence[Camera], images: Sequence[np.ndarray],
                  masks: Sequence[np.ndarray | None], config: InitConfig,
                  subjects: Sequence[np.ndarray | None], static: PointCloud, budget: int,
                  seed: int, threads: int) -> Seed:
    """A later key frame of a scene: the static seeds kept, the subject fused from its own
    views' depth inside the grown subject masks (its room: the budget the static part leaves,
    at least a tenth of it)."""
    rig = RigGeometry(cameras, images, masks, config.stereo,
                      depth_masks=_grown(subjects, SUBJECT_DILATE), threads=threads)
    fused = rig.fused().cloud
    subject = fused.subset(subject_hull(fused.points, cameras, subjects))
    room = max(budget - len(static), budget // 10)
    subject = _sample(subject, room, seed)
    return _joined([("static", static), ("subject", subject)],
                   f"seeded with {len(static)} static-scene points kept from the first key "
                   f"frame + {len(subject)} subject points fused from this frame's stereo depth")


def _joined(parts: list[tuple[str, PointCloud]], note: str) -> Seed:
    pts = np.concatenate([p.points for _, p in parts])
    cols = np.concatenate([p.colors if p.colors is not None else np.full((len(p), 3), 0.5)
                           for _, p in parts])
    return Seed(torch.from_numpy(pts).float(), torch.from_numpy(cols).float(), note, parts)
