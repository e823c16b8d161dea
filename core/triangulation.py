"""Sparse points from a capture's known poses: what a studio rig that ships calibration but no
point cloud seeds training with.

SIFT features (Lowe 2004) in every view; each camera is matched with its nearest neighbours
(centres close, optical axes within `max_axis_angle`); a match must pass Lowe's ratio test, be
mutual, and lie within `max_epipolar` pixels of its epipolar line (the poses are known, so no
RANSAC is needed). COLMAP's point triangulator (pycolmap, Schoenberger and Frahm 2016) makes
the points from those matches with every camera's pose and intrinsics fixed: it builds the
tracks from the correspondence graph, triangulates, merges, completes and filters them
(reprojection below `max_reprojection` pixels, rays meeting at `min_angle_deg` or more) and
refines the points by bundle adjustment with the poses constant
(docs/decisions/2026-11-29-sparse-points-pycolmap-or-ours.md: more points as accurate as our
own DLT tracks, in about the same time). With masks, a point must project onto the foreground
of every view it falls in (the visual hull), and fall in three views or more (a wrong match
along two views' epipolar lines, outside every other view, is not carved by any). Colour: the
mean of the images at its observations.

Torch-free (numpy, OpenCV, pycolmap); images in 0..1, cameras ideal pinholes (undistorted).
"""

from __future__ import annotations

import math
import signal
import tempfile
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from core.data.capture import Camera
from core.data.points import PointCloud

_TERM = signal.getsignal(signal.SIGTERM)
import pycolmap  # noqa: E402  (between the two halves of keeping SIGTERM's handler)

# COLMAP's logging (glog) takes SIGTERM when pycolmap is imported, to print a stack trace and
# end the process: a worker told to stop by SIGTERM must checkpoint and give its job back
# instead (worker.runner), so Python's handler is put back. (The fatal signals keep glog's.)
if _TERM is not None and threading.current_thread() is threading.main_thread():
    signal.signal(signal.SIGTERM, _TERM)

__all__ = ["TriangulationConfig", "TriangulationStats", "camera_pairs", "in_visual_hull",
           "pixel_indices", "triangulate_views"]


@dataclass(frozen=True)
class TriangulationConfig:
    """How sparse points are made from known poses."""

    neighbours: int = 6
    """Cameras each camera is matched with (nearest centres among those looking the same way)."""
    max_axis_angle: float = 75.0
    """Largest angle (degrees) between two matched cameras' optical axes."""
    max_features: int = 8000
    """SIFT features kept per view (strongest first)."""
    ratio: float = 0.8
    """Lowe's ratio test: best match distance below this times the second best (Lowe 2004)."""
    max_epipolar: float = 1.5
    """Largest distance (pixels) of a match from its epipolar line."""
    max_reprojection: float = 4.0
    """Largest reprojection error (pixels) of an observation that a track merges, completes or
    keeps (COLMAP's default)."""
    min_angle_deg: float = 1.5
    """Smallest angle between the rays of a kept point (depth is ill-posed below; COLMAP's
    default)."""


@dataclass
class TriangulationStats:
    """What triangulation found, for the run's notes."""

    features: int = 0
    pairs: int = 0
    matches: int = 0
    tracks: int = 0
    """Points the triangulator made, before the visual hull carved them."""
    points: int = 0
    observations: int = 0
    """Observations of the kept points (the sum of their track lengths)."""
    reprojection: float = 0.0
    """Mean reprojection error (pixels) over those observations."""


def camera_pairs(cameras: Sequence[Camera], neighbours: int,
                 max_axis_angle: float = 75.0) -> list[tuple[int, int]]:
    """Pairs (i, j), i < j: each camera with its `neighbours` nearest (by centre) cameras whose
    optical axes are within `max_axis_angle` degrees of its own."""
    centers = np.stack([c.center for c in cameras])
    axes = np.stack([c.R[2] / np.linalg.norm(c.R[2]) for c in cameras])
    cos_max = math.cos(math.radians(max_axis_angle))
    pairs: set[tuple[int, int]] = set()
    for i in range(len(cameras)):
        dist = np.linalg.norm(centers - centers[i], axis=1)
        ok = (axes @ axes[i] >= cos_max) & (np.arange(len(cameras)) != i)
        for j in np.flatnonzero(ok)[np.argsort(dist[ok], kind="stable")][:neighbours]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def _features(image: np.ndarray, mask: np.ndarray | None, max_features: int):
    """SIFT keypoints as (K, 2) pixel coordinates (centres at +0.5) and (K, 128) descriptors."""
    grey = cv2.cvtColor((np.clip(image[..., :3], 0, 1) * 255 + 0.5).astype(np.uint8),
                        cv2.COLOR_RGB2GRAY)
    fg = None if mask is None else ((mask[..., 0] > 0.5) * 255).astype(np.uint8)
    kps, desc = cv2.SIFT_create(nfeatures=max_features).detectAndCompute(grey, fg)
    if desc is None or not kps:
        return np.zeros((0, 2)), np.zeros((0, 128))
    # OpenCV puts pixel centres at integer coordinates; ours are at +0.5 (docs/design.md 3.1).
    return np.array([k.pt for k in kps], dtype=np.float64) + 0.5, desc.astype(np.float64)


def _fundamental(a: Camera, b: Camera) -> np.ndarray:
    """F with x_b^T F x_a = 0 for pixel coordinates of the same point in cameras a and b."""
    R = b.R @ a.R.T
    t = b.t - R @ a.t
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(b.K).T @ tx @ R @ np.linalg.inv(a.K)


def _best_two(keys: np.ndarray, dist: np.ndarray, other: np.ndarray, ratio: float
              ) -> dict[int, int]:
    """{key: other of its nearest candidate} for keys whose nearest candidate passes the ratio
    test against their second nearest (a key with one candidate passes)."""
    order = np.lexsort((dist, keys))
    keys, dist, other = keys[order], dist[order], other[order]
    first = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    has_second = np.r_[first[1:], len(keys)] - first > 1
    second = np.where(has_second, dist[np.minimum(first + 1, len(keys) - 1)], np.inf)
    ok = dist[first] < ratio * ratio * second  # squared distances
    return dict(zip(keys[first][ok].tolist(), other[first][ok].tolist()))


def _match(xa: np.ndarray, da: np.ndarray, xb: np.ndarray, db: np.ndarray, F: np.ndarray,
           config: TriangulationConfig) -> np.ndarray:
    """(M, 2) feature indices (a, b): guided by the known epipolar geometry, each feature's
    candidates are the features within `max_epipolar` pixels of its epipolar line (both ways);
    a match is the nearest candidate in descriptor space both ways, passing Lowe's ratio test
    among the candidates. Exact and deterministic; the epipolar constraint, not the ratio over
    the whole image, tells apart the repeats of a pattern."""
    if not len(xa) or not len(xb):
        return np.zeros((0, 2), dtype=np.int64)
    ha, hb = np.c_[xa, np.ones(len(xa))], np.c_[xb, np.ones(len(xb))]
    la, lb = ha @ F.T, hb @ F  # lines in b of the points of a, lines in a of those of b
    la /= np.maximum(np.hypot(la[:, :1], la[:, 1:2]), 1e-12)
    lb /= np.maximum(np.hypot(lb[:, :1], lb[:, 1:2]), 1e-12)
    rows, cols, dists = [], [], []
    nb2 = np.einsum("ij,ij->i", db, db)
    for start in range(0, len(xa), 1024):  # bounded memory: 1024 x |b| at a time
        a = slice(start, start + 1024)
        near = (np.abs(la[a] @ hb.T) < config.max_epipolar) & \
            (np.abs(ha[a] @ lb.T) < config.max_epipolar)
        i, j = np.nonzero(near)
        d2 = np.einsum("ij,ij->i", da[a][i], da[a][i]) + nb2[j] - 2 * np.einsum(
            "ij,ij->i", da[a][i], db[j])
        rows.append(i + start)
        cols.append(j)
        dists.append(d2)
    i, j, d2 = np.concatenate(rows), np.concatenate(cols), np.concatenate(dists)
    if not len(i):
        return np.zeros((0, 2), dtype=np.int64)
    ab, ba = _best_two(i, d2, j, config.ratio), _best_two(j, d2, i, config.ratio)
    pairs = [(x, y) for x, y in ab.items() if ba.get(y) == x]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def pixel_indices(uv: np.ndarray, width: int, height: int,
                  z: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer pixel (u, v) of continuous coordinates (N, 2), clipped into the image, and
    whether each lies inside it (and in front, z > 0, when depths are given)."""
    u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    inside = (u >= 0) & (v >= 0) & (u < width) & (v < height)
    if z is not None:
        inside &= z > 0
    return np.clip(u, 0, width - 1), np.clip(v, 0, height - 1), inside


def in_visual_hull(points: np.ndarray, cameras: Sequence[Camera],
                   masks: Sequence[np.ndarray | None]) -> np.ndarray:
    """(N,) whether each point lands on foreground (mask > 0.5) in every view with a mask
    (H, W, 1) that it projects into."""
    ok = np.ones(len(points), dtype=bool)
    for cam, mask in zip(cameras, masks):
        if mask is not None:
            uv, z = cam.project(points)
            u, v, inside = pixel_indices(uv, cam.width, cam.height, z)
            ok &= ~inside | (mask[v, u, 0] > 0.5)
    return ok


def triangulate_views(cameras: Sequence[Camera], images: Sequence[np.ndarray],
                      masks: Sequence[np.ndarray | None] | None = None,
                      config: TriangulationConfig = TriangulationConfig()
                      ) -> tuple[PointCloud, TriangulationStats]:
    """Sparse points seen by the cameras (ideal pinholes) in their images (H, W, 3) in 0..1,
    with their mean colours; masks (H, W, 1) restrict features to, and carve points by, the
    foreground. Returns the cloud (possibly empty) and counts of each step."""
    if len(images) != len(cameras) or (masks is not None and len(masks) != len(cameras)):
        raise ValueError(f"images, masks: expected {len(cameras)} of each")
    masks = list(masks) if masks is not None else [None] * len(cameras)
    stats = TriangulationStats()
    feats = [_features(img, m, config.max_features) for img, m in zip(images, masks)]
    stats.features = sum(len(f[0]) for f in feats)
    matches = []
    for a, b in camera_pairs(cameras, config.neighbours, config.max_axis_angle):
        m = _match(feats[a][0], feats[a][1], feats[b][0], feats[b][1],
                   _fundamental(cameras[a], cameras[b]), config)
        matches.append((a, b, m))
        stats.pairs += 1
        stats.matches += len(m)
    empty = PointCloud(np.zeros((0, 3)), np.zeros((0, 3), np.float32))
    if not stats.matches:
        return empty, stats
    points, tracks = _colmap_points(cameras, [f[0] for f in feats], matches, config)
    stats.tracks = len(points)
    if not len(points):
        return empty, stats
    point, view, xy = _observations(tracks, [f[0] for f in feats])
    colors = _mean_per_point(point, _colours_at(view, xy, images), len(points))
    cloud = PointCloud(points, np.clip(colors, 0, 1).astype(np.float32))
    hull = in_visual_hull(points, cameras, masks)
    if any(m is not None for m in masks):  # the hull carves only where views overlap
        hull &= _views_inside(points, cameras) >= min(3, len(cameras))
    cloud = cloud.subset(hull)
    stats.points = len(cloud)
    err = np.zeros(len(point))
    for v in np.unique(view):
        at = view == v
        err[at] = np.linalg.norm(cameras[v].project(points[point[at]])[0] - xy[at], axis=1)
    kept = hull[point]
    stats.observations = int(kept.sum())
    stats.reprojection = float(err[kept].mean()) if kept.any() else 0.0
    return cloud, stats


def _colmap_points(cameras: Sequence[Camera], keypoints: Sequence[np.ndarray],
                   matches: Sequence[tuple[int, int, np.ndarray]], config: TriangulationConfig
                   ) -> tuple[np.ndarray, list[np.ndarray]]:
    """COLMAP's point triangulator (pycolmap) on our features and matches with every camera's
    pose and intrinsics fixed: points (P, 3) and per point its track (L, 2) of (view, feature
    index). COLMAP reads them from a database: one camera, rig and frame per view, the matches
    as calibrated two-view geometries (their inliers: the epipolar filter has verified them)."""
    pycolmap.logging.minloglevel = 2  # its progress log is per image: warnings and errors
    with tempfile.TemporaryDirectory(prefix="dgs-triangulation-") as tmp:
        db_path = Path(tmp) / "database.db"
        rec = pycolmap.Reconstruction()
        with pycolmap.Database.open(db_path) as db:
            for i, (cam, xy) in enumerate(zip(cameras, keypoints)):
                key = i + 1  # COLMAP's ids start at 1
                K = cam.K
                camera = pycolmap.Camera(camera_id=key, model="PINHOLE", width=cam.width,
                                         height=cam.height,
                                         params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
                rig = pycolmap.Rig(rig_id=key)
                rig.add_ref_sensor(camera.sensor_id)
                image = pycolmap.Image(name=f"{i}", camera_id=key, image_id=key)
                image.frame_id = key
                frame = pycolmap.Frame(frame_id=key, rig_id=key)
                frame.add_data_id(image.data_id)
                db.write_camera(camera, use_camera_id=True)
                db.write_rig(rig, use_rig_id=True)
                db.write_frame(frame, use_frame_id=True)
                db.write_image(image, use_image_id=True)
                db.write_keypoints(key, np.asarray(xy, np.float32).reshape(-1, 2))
                frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R), cam.t)
                rec.add_camera(camera)
                rec.add_rig(rig)
                rec.add_frame(frame)
                rec.add_image(image)
            for a, b, m in matches:
                m = np.ascontiguousarray(m, np.uint32).reshape(-1, 2)
                db.write_matches(a + 1, b + 1, m)
                db.write_two_view_geometry(a + 1, b + 1, pycolmap.TwoViewGeometry(
                    config=pycolmap.TwoViewGeometryConfiguration.CALIBRATED,
                    inlier_matches=m))
        for i in range(len(cameras)):
            rec.register_frame(i + 1)
        options = pycolmap.IncrementalPipelineOptions(
            num_threads=max(1, cv2.getNumThreads()), random_seed=0, extract_colors=False,
            min_num_matches=1)  # every verified pair counts, however few its matches
        options.triangulation.ignore_two_view_tracks = False  # ours are seeds: keep them
        options.triangulation.random_seed = 0
        options.triangulation.min_angle = config.min_angle_deg
        options.triangulation.merge_max_reproj_error = config.max_reprojection
        options.triangulation.complete_max_reproj_error = config.max_reprojection
        options.mapper.filter_max_reproj_error = config.max_reprojection
        options.mapper.filter_min_tri_angle = config.min_angle_deg
        (Path(tmp) / "sparse").mkdir()
        out = pycolmap.triangulate_points(rec, db_path, tmp, Path(tmp) / "sparse",
                                          clear_points=True, options=options)
    ids = sorted(out.points3D.keys())
    points = np.array([out.points3D[p].xyz for p in ids], np.float64).reshape(-1, 3)
    tracks = [np.array([(e.image_id - 1, e.point2D_idx) for e in out.points3D[p].track.elements],
                       np.int64).reshape(-1, 2) for p in ids]
    return points, tracks


def _views_inside(points: np.ndarray, cameras: Sequence[Camera]) -> np.ndarray:
    """(N,) in how many of the cameras' images each point lands (in front). A matted subject
    is where the views overlap; a point inside only the two views that matched it (a wrong
    match along their epipolar lines) is one no third view's mask can carve."""
    count = np.zeros(len(points), np.int64)
    for cam in cameras:
        uv, z = cam.project(points)
        count += pixel_indices(uv, cam.width, cam.height, z)[2]
    return count


def _observations(tracks: list[np.ndarray], keypoints: Sequence[np.ndarray]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every observation of the tracks: its point's index, its view and pixel coordinates."""
    point = np.repeat(np.arange(len(tracks)), [len(t) for t in tracks])
    flat = np.concatenate(tracks)
    xy = np.zeros((len(flat), 2))
    for v in np.unique(flat[:, 0]):
        at = flat[:, 0] == v
        xy[at] = keypoints[v][flat[at, 1]]
    return point, flat[:, 0], xy


def _colours_at(view: np.ndarray, xy: np.ndarray, images: Sequence[np.ndarray]) -> np.ndarray:
    out = np.zeros((len(view), 3))
    for v in np.unique(view):
        at = view == v
        img = images[v]
        u, y, _ = pixel_indices(xy[at], img.shape[1], img.shape[0])
        out[at] = img[y, u, :3]
    return out


def _mean_per_point(point: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    sums = np.zeros((n, values.shape[1]))
    np.add.at(sums, point, values)
    return sums / np.maximum(np.bincount(point, minlength=n), 1)[:, None]
