"""Whether a rig's poses are the wrong way round: camera-to-world poses in a field that holds
world-to-camera ones, or the reverse (the rule of `core.data.importers.rig.settle_rig`).

Nothing in one pose says which way it goes; a rig says it. Read the right way, a capture's
cameras film a subject: most of them see one point, from directions far apart. Read the wrong
way, an inward rig becomes cameras that look away from each other, or that all sit at one
point. :func:`shared_view` measures a reading; :func:`looks_inverted` is the rule, refusing only
when the reading given is no rig and the other reading surrounds its subject, so a forward-
facing capture (whose other reading is forward-facing too) and any rig whose other reading is no
better import as given. The thresholds, and the rigs they were measured on: docs/decisions/
2026-11-29-mirrored-and-inverted-poses.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from core.data.capture import Camera, CaptureError, Problem
from core.data.importers.common import ImportedCapture

__all__ = ["AGREEMENT_MARGIN", "BASELINE_AT_MOST", "DIRECTION_MIN_CAMERAS", "GIVEN_AT_MOST",
           "OTHER_AT_LEAST", "OTHER_SPREAD", "UPRIGHT_AT_MOST", "SharedView", "check_direction",
           "looks_inverted", "other_way", "shared_view"]

DIRECTION_MIN_CAMERAS = 4
"""Fewer cameras are too little evidence of which way their poses go."""
GIVEN_AT_MOST = 0.5
"""As given, the rig is no rig when at most this fraction of its cameras see one point..."""
BASELINE_AT_MOST = 0.05
"""...or when its cameras sit at one point: their centres spread by at most this fraction of
their distance to the point they share (no baseline, nothing to triangulate)."""
UPRIGHT_AT_MOST = 0.5
"""...or, where the format fixes the world's up, when its cameras are not held along it: the
mean of their images' up directions reaches this far along it or less (a rig is held upright,
give or take its tilt; the other reading of an upright rig points its cameras' tops every way,
and is a rig by every other measure when that up is the world's z)."""
OTHER_AT_LEAST = 0.9
"""Read the other way, at least this fraction of the cameras see one point..."""
OTHER_SPREAD = 90.0
"""...with optical axes at least this many degrees apart (a rig around its subject; an upright
rig's other reading is a forward-facing huddle whichever way its cameras look)..."""
AGREEMENT_MARGIN = 0.35
"""...and agreeing on up (`SharedView.upright`) no more than this much worse than as given: a
panorama, all its cameras upright, is not taken for the inverse of a dome whose other reading
tumbles (inverted upright rigs measured at most 0.28 more agreed than the rig itself)."""
_COUNTED, _AXES, _DEPTHS = 256, 32, 2.0 ** np.arange(-2, 7)
_OTHER = {"world_to_camera": "camera-to-world", "camera_to_world": "world-to-camera"}
_FIX = {
    "world_to_camera": "Invert each matrix, or give the poses in a format that holds "
                       "camera-to-world (transforms.json, with OpenGL camera axes)",
    "camera_to_world": "Invert each matrix, or give the poses in a format that holds "
                       "world-to-camera (a COLMAP model, with OpenCV camera axes)",
}


@dataclass(frozen=True)
class SharedView:
    """How a rig's cameras share a view (:func:`shared_view`)."""

    seen: int
    """The most cameras that see one point."""
    counted: int
    """The cameras counted (up to 256, evenly spread)."""
    spread: float
    """The angle the optical axes span, in degrees (twice the largest angle from their mean
    axis): a few degrees for a forward-facing rig, about 180 for a ring."""
    baseline: float
    """How far apart the cameras are, relative to their distance from that point (the
    centres' median distance from their median over the median distance to the point)."""
    upright: float
    """How well the cameras agree on which way is up: the length of the mean of their image's
    up directions (-y) in the world, 1 when all agree, near 0 when they point every way."""
    along_up: float | None = None
    """Where the format fixes the world's up (transforms.json: +z): that mean along it, 1 for
    cameras held upright, 0 on their sides or half upside down; None where it does not."""


def other_way(cameras: Sequence[Camera], camera_axes: np.ndarray) -> list[Camera]:
    """The cameras the source would give if its pose field held the other direction: each
    world-to-camera ``A^-1 inv(E) A``, ``A`` the source's camera axes in ours (the import
    record's ``source_camera_from_camera``: OpenGL's for transforms.json, else the identity)."""
    A = np.asarray(camera_axes, np.float64)
    A_inv = np.linalg.inv(A)
    return [replace(c, world_to_camera=A_inv @ np.linalg.inv(c.world_to_camera) @ A)
            for c in cameras]


def _evenly(items: Sequence, most: int) -> list:
    picks = np.linspace(0, len(items) - 1, min(len(items), most)).round().astype(int)
    return [items[i] for i in sorted(set(picks.tolist()))]


def shared_view(cameras: Sequence[Camera], up: Sequence[float] | None = None) -> SharedView:
    """How many cameras see one point (in front, inside the image, distortion ignored), how
    far their axes spread, how far apart they stand and how upright they are (along `up`, the
    world's up where the format fixes it). The points tried lie on the optical axes of up to
    32 cameras at depths 1/4 to 64 times the rig's size, plus the point nearest every axis; up
    to 256 cameras, evenly spread, are counted."""
    counted = _evenly(cameras, _COUNTED)
    w2c = np.stack([c.world_to_camera for c in counted])
    K = np.stack([c.K for c in counted])
    size = np.array([(c.width, c.height) for c in counted], np.float64)
    R, t = w2c[:, :3, :3], w2c[:, :3, 3]
    # Positions near float64's limit overflow below to inf or nan, which no comparison passes:
    # nothing is seen, read either way, so such a rig is never refused.
    with np.errstate(all="ignore"):
        centres = -np.einsum("nji,nj->ni", R, t)
        axes = R[:, 2, :]  # each camera's +z in the world
        spread = float(np.median(np.linalg.norm(centres - np.median(centres, axis=0), axis=1)))
        points = _candidates(centres, axes, spread)
        cam = np.einsum("nij,pj->npi", R, points) + t[:, None, :]  # (cameras, points, 3)
        z = cam[..., 2]
        x, y = cam[..., 0] / z, cam[..., 1] / z
        u = K[:, 0, 0, None] * x + K[:, 0, 1, None] * y + K[:, 0, 2, None]
        v = K[:, 1, 1, None] * y + K[:, 1, 2, None]
        seen = ((z > 0) & (u >= 0) & (u <= size[:, 0, None]) & (v >= 0)
                & (v <= size[:, 1, None])).sum(axis=0)
        best = points[int(np.argmax(seen))]
        distance = float(np.median(np.linalg.norm(centres - best, axis=1)))
    mean = axes.mean(axis=0)
    mean = mean / max(float(np.linalg.norm(mean)), 1e-12)
    widest = float(np.degrees(np.arccos(np.clip(axes @ mean, -1.0, 1.0))).max())
    tops = -R[:, 1, :].mean(axis=0)  # the mean of the images' up directions
    along = None if up is None else float(tops @ np.asarray(up, np.float64))
    with np.errstate(all="ignore"):
        baseline = spread / distance if distance > 0 else 0.0
    baseline = baseline if np.isfinite(baseline) else 0.0
    return SharedView(int(seen.max()), len(counted), min(2.0 * widest, 360.0), baseline,
                      float(np.linalg.norm(tops)), along)


def _candidates(centres: np.ndarray, axes: np.ndarray, spread: float) -> np.ndarray:
    """Points along the optical axes of up to 32 cameras, at depths scaled by the rig's size
    (`spread`, or the centres' distance from the origin when they coincide), and the point
    nearest every axis."""
    scale = spread
    if not scale > 1e-9 * max(1.0, float(np.abs(centres).max())):
        scale = float(np.median(np.linalg.norm(centres, axis=1))) or 1.0
    picked = np.array(_evenly(range(len(centres)), _AXES))
    along = centres[picked, None, :] + scale * _DEPTHS[None, :, None] * axes[picked, None, :]
    # The point nearest every axis: sum_i (I - a_i a_i^T) (X - c_i) = 0.
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    lhs, rhs = proj.sum(axis=0), np.einsum("nij,nj->i", proj, centres)
    if not (np.isfinite(lhs).all() and np.isfinite(rhs).all()):
        return along.reshape(-1, 3)  # LAPACK does not converge on these
    nearest = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    return np.concatenate([along.reshape(-1, 3), nearest[None]])


def _a_rig(view: SharedView) -> bool:
    """A reading that films something: most cameras share a view, from places apart, held
    upright where the world's up is known (the limits above)."""
    return (view.seen > GIVEN_AT_MOST * view.counted and view.baseline > BASELINE_AT_MOST
            and (view.along_up is None or view.along_up > UPRIGHT_AT_MOST))


def looks_inverted(given: SharedView, other: SharedView) -> bool:
    """The rule: the poses go the other way when, as given, the rig is no rig (at most
    `GIVEN_AT_MOST` of its cameras see one point, or they stand within `BASELINE_AT_MOST`, or,
    where the format fixes the world's up, they are held along it no more than
    `UPRIGHT_AT_MOST`) and read the other way it is a rig (by the same measures) around its
    subject: at least `OTHER_AT_LEAST` see one point, from axes `OTHER_SPREAD` degrees apart or
    more, agreeing on up not `AGREEMENT_MARGIN` worse than given. Fewer than
    `DIRECTION_MIN_CAMERAS` cameras are never refused."""
    return (given.counted >= DIRECTION_MIN_CAMERAS and not _a_rig(given) and _a_rig(other)
            and other.seen >= OTHER_AT_LEAST * other.counted and other.spread >= OTHER_SPREAD
            and other.upright >= given.upright - AGREEMENT_MARGIN)


def check_direction(imported: ImportedCapture) -> None:
    """CaptureError naming the pose field and the fix when `imported`'s poses look the other
    way round (:func:`looks_inverted`); nothing when they do not, or cannot (projections)."""
    poses = imported.poses
    if poses is None or poses.holds not in _OTHER or poses.solved:
        return
    if len(imported.cameras) < DIRECTION_MIN_CAMERAS:
        return
    given = shared_view(imported.cameras, poses.up)
    if _a_rig(given):
        return  # nothing more to measure
    axes = (imported.record.get("to_source") or {}).get("source_camera_from_camera")
    other = shared_view(other_way(imported.cameras, np.eye(4) if axes is None else axes),
                        poses.up)
    if not looks_inverted(given, other):
        return
    n = given.counted
    how = (f"the cameras look away from each other (at most {given.seen} of {n} see any one "
           "point)" if given.seen <= GIVEN_AT_MOST * n else "the cameras all stand at one point"
           if given.baseline <= BASELINE_AT_MOST else "the cameras are not held upright along "
           f"the world's up ({', '.join(f'{v:g}' for v in poses.up or ())})")
    raise CaptureError([Problem(str(poses.file), (
        f"{poses.field}: these look like {_OTHER[poses.holds]} poses, but this field holds "
        f"{poses.holds.replace('_', '-')} ones: as given, {how}; inverted, {other.seen} of {n} "
        f"see one point from axes {other.spread:.0f} degrees apart. "
        f"{_FIX[poses.holds]}"))])
