"""Sparse points from a capture's known poses: what a studio rig that ships calibration but no
point cloud seeds training with.

SIFT features (Lowe 2004) in every view; each camera is matched with its nearest neighbours
(centres close, optical axes within `max_axis_angle`); a match must pass Lowe's ratio test, be
mutual, and lie within `max_epipolar` pixels of its epipolar line (the poses are known, so no
RANSAC is needed). Matches chain into tracks (connected components of (view, feature) pairs);
each track with one feature per view is triangulated by linear least squares (DLT) on
normalised image coordinates and kept when it lies in front of every camera that sees it, its
largest reprojection error is below `max_reprojection` pixels and its rays meet at
`min_angle_deg` or more. With masks, a point must project onto the foreground of every view it
falls in (the visual hull). Colour: the mean of the images at its observations.

Torch-free (numpy, OpenCV, SciPy); images in 0..1, cameras ideal pinholes (undistorted).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from core.data.capture import Camera
from core.data.points import PointCloud

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
    max_reprojection: float = 1.5
    """Largest reprojection error (pixels) of a kept point in any view that sees it."""
    min_angle_deg: float = 2.0
    """Smallest largest angle between the rays of a kept point (depth is ill-posed below)."""


@dataclass
class TriangulationStats:
    """What triangulation found, for the run's notes."""

    features: int = 0
    pairs: int = 0
    matches: int = 0
    tracks: int = 0
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


def _tracks(offsets: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Connected components of the match graph: (node ids, component labels) of the nodes in
    components of two or more nodes, sorted by label."""
    n = int(offsets[-1])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels)
    nodes = np.flatnonzero(sizes[labels] >= 2)
    order = np.argsort(labels[nodes], kind="stable")
    return nodes[order], labels[nodes][order]


def _dlt(rays: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(T, 3) points from (T, L, 2) normalised coordinates and (T, L, 3, 4) [R | t] poses."""
    x, y = rays[..., 0:1], rays[..., 1:2]
    rows = np.concatenate([x * poses[..., 2, :] - poses[..., 0, :],
                           y * poses[..., 2, :] - poses[..., 1, :]], axis=1)  # (T, 2L, 4)
    _, _, vt = np.linalg.svd(rows)
    h = vt[:, -1]
    w = np.where(np.abs(h[:, 3:]) > 1e-12, h[:, 3:], 1e-12)
    return h[:, :3] / w


def _triangulate_tracks(views: np.ndarray, coords: np.ndarray, cameras: Sequence[Camera],
                        config: TriangulationConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For tracks of one length L, views (T, L) and pixel coordinates (T, L, 2): points (T, 3),
    whether each is kept (T,), and each observation's reprojection error (T, L), infinite
    behind the camera."""
    Kinv = np.stack([np.linalg.inv(c.K) for c in cameras])
    poses = np.stack([c.world_to_camera[:3] for c in cameras])
    h = np.concatenate([coords, np.ones(coords.shape[:2] + (1,))], axis=2)
    rays = np.einsum("tlij,tlj->tli", Kinv[views], h)[..., :2]
    pts = _dlt(rays, poses[views])
    cam = np.einsum("tlij,tj->tli", poses[views][..., :3], pts) + poses[views][..., 3]
    z = np.where(cam[..., 2:] > 1e-9, cam[..., 2:], 1e-9)
    proj = np.einsum("tlij,tlj->tli", np.stack([c.K for c in cameras])[views], cam / z)[..., :2]
    err = np.where(cam[..., 2] > 1e-9, np.linalg.norm(proj - coords, axis=2), np.inf)
    centers = np.stack([c.center for c in cameras])[views]
    dirs = pts[:, None] - centers
    dirs /= np.maximum(np.linalg.norm(dirs, axis=2, keepdims=True), 1e-12)
    cos = np.einsum("tai,tbi->tab", dirs, dirs).min(axis=(1, 2))
    angle_ok = cos <= math.cos(math.radians(config.min_angle_deg))
    return pts, (err.max(axis=1) < config.max_reprojection) & angle_ok, err


def _robust_tracks(groups: dict[int, tuple[np.ndarray, np.ndarray]], cameras: Sequence[Camera],
                   config: TriangulationConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate tracks grouped by length {L: (views (T, L), coords (T, L, 2))}, longest
    first; a track that fails loses its worst observation and is tried again one shorter, down
    to two views (a wrong match in a chain, or a feature repeated at one spot, costs that
    observation, not the track). Returns points (P, 3) and the kept tracks' views (P, L) and
    coordinates (P, L, 2) as lists per length."""
    out_pts, out_views, out_coords = [], [], []
    for length in range(max(groups, default=0), 1, -1):
        if length not in groups:
            continue
        views, coords = groups.pop(length)
        pts, ok, err = _triangulate_tracks(views, coords, cameras, config)
        out_pts.append(pts[ok])
        out_views.append(views[ok])
        out_coords.append(coords[ok])
        bad = np.flatnonzero(~ok)
        if length > 2 and len(bad):
            keep = np.ones((len(bad), length), dtype=bool)
            keep[np.arange(len(bad)), err[bad].argmax(axis=1)] = False
            shorter = (views[bad][keep].reshape(len(bad), length - 1),
                       coords[bad][keep].reshape(len(bad), length - 1, 2))
            if length - 1 in groups:
                shorter = tuple(np.concatenate([a, b]) for a, b in zip(groups[length - 1],
                                                                        shorter))
            groups[length - 1] = shorter
    return out_pts, out_views, out_coords


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
    offsets = np.concatenate([[0], np.cumsum([len(f[0]) for f in feats])]).astype(np.int64)
    edges = []
    for a, b in camera_pairs(cameras, config.neighbours, config.max_axis_angle):
        m = _match(feats[a][0], feats[a][1], feats[b][0], feats[b][1],
                   _fundamental(cameras[a], cameras[b]), config)
        if len(m):
            edges.append(np.stack([m[:, 0] + offsets[a], m[:, 1] + offsets[b]], axis=1))
        stats.pairs += 1
        stats.matches += len(m)
    empty = PointCloud(np.zeros((0, 3)), np.zeros((0, 3), np.float32))
    if not edges or not sum(len(e) for e in edges):
        return empty, stats
    nodes, labels = _tracks(offsets, np.concatenate(edges))
    view_of = np.searchsorted(offsets, nodes, side="right") - 1
    starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]])
    lengths = np.diff(np.r_[starts, len(nodes)])
    coords_all = np.concatenate([f[0] for f in feats])[nodes]
    groups = {}
    for length in np.unique(lengths):
        if length > 2 * len(cameras):  # a chain of wrong matches, not one point
            continue
        sel = starts[lengths == length][:, None] + np.arange(length)  # (T, L) node positions
        groups[int(length)] = (view_of[sel], coords_all[sel])
        stats.tracks += len(sel)
    points, views, coords = _robust_tracks(groups, cameras, config)
    colors = [_track_colours(v, c, images) for v, c in zip(views, coords)]
    cloud = PointCloud(np.concatenate(points), np.concatenate(colors).astype(np.float32))
    hull = in_visual_hull(cloud.points, cameras, masks)
    cloud = cloud.subset(hull)
    stats.points = len(cloud)
    counts, errors = _observation_errors(points, views, coords, cameras)
    stats.observations = int(counts[hull].sum())
    stats.reprojection = float(errors[hull].sum() / max(stats.observations, 1))
    return cloud, stats


def _observation_errors(points: list[np.ndarray], views: list[np.ndarray],
                        coords: list[np.ndarray], cameras: Sequence[Camera]
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Per kept point (in `points`' order): its track length and the sum of its observations'
    reprojection errors (pixels)."""
    counts, sums = [], []
    for pts, v, xy in zip(points, views, coords):
        err = np.zeros(v.shape)
        for i in np.unique(v):
            where = v == i
            uv, _ = cameras[i].project(pts[np.nonzero(where)[0]])
            err[where] = np.linalg.norm(uv - xy[where], axis=1)
        counts.append(np.full(len(pts), v.shape[1]))
        sums.append(err.sum(axis=1))
    return np.concatenate(counts), np.concatenate(sums)


def _track_colours(views: np.ndarray, coords: np.ndarray,
                   images: Sequence[np.ndarray]) -> np.ndarray:
    acc = np.zeros(views.shape + (3,))
    for v in np.unique(views):
        where = views == v
        img = images[v]
        u, y, _ = pixel_indices(coords[where], img.shape[1], img.shape[0])
        acc[where] = img[y, u, :3]
    return np.clip(acc.mean(axis=1), 0, 1)
