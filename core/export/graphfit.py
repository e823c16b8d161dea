"""The stream's deformation graph of a group and its node transforms, fitted at export time.

The run's tracker builds a new graph on every frame from the previous one and does not keep its
node parameters; the stream instead needs one graph per group, in the key frame's space, and
per frame the transforms that carry key space to that frame. They are fitted from the tracked
Gaussians themselves (track ids give the correspondence): per node a weighted Kabsch fit of the
Gaussians it carries (weights: their blend weights), then the translations re-solved jointly by
linear least squares on the blended prediction, which is what the decoder evaluates
(docs/benchmarks.md compares the two and measures what the residuals then cost).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.sparse import csr_matrix
from scipy.sparse.linalg import lsqr

from core.rotations import quat_to_rotmat, rotmat_to_quat
from core.sequence.graph import farthest_point_sampling

__all__ = ["anchor_weights", "fit_node_transforms", "graph_nodes", "nearest_nodes"]


def graph_nodes(points: np.ndarray, count: int) -> np.ndarray:
    """(count, 3) farthest-point samples of `points`, as `core.sequence.graph` picks them."""
    pts = torch.from_numpy(np.ascontiguousarray(points, np.float32))
    return points[farthest_point_sampling(pts, count).numpy()].astype(np.float32)


def nearest_nodes(points: np.ndarray, nodes: np.ndarray, k: int,
                  chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    """(distances, indices) (N, k) of the k nearest nodes to each point, ascending."""
    dist = np.empty((len(points), k), np.float32)
    idx = np.empty((len(points), k), np.int64)
    n2 = (nodes.astype(np.float64) ** 2).sum(1)
    for s in range(0, len(points), chunk):
        p = points[s:s + chunk].astype(np.float64)
        d2 = np.maximum((p * p).sum(1)[:, None] - 2 * p @ nodes.T.astype(np.float64) + n2, 0)
        part = np.argpartition(d2, k - 1, axis=1)[:, :k] if k < len(nodes) else \
            np.tile(np.arange(len(nodes)), (len(p), 1))
        pd = np.take_along_axis(d2, part, 1)
        order = np.argsort(pd, axis=1, kind="stable")
        idx[s:s + chunk] = np.take_along_axis(part, order, 1)
        dist[s:s + chunk] = np.sqrt(np.take_along_axis(pd, order, 1))
    return dist, idx


def anchor_weights(points: np.ndarray, nodes: np.ndarray, k: int = 4):
    """(anchors (N, k) uint16, weight codes (N, k) uint8) of `points`: the k nearest nodes with
    (1 - d / d_(k+1))^2 (`core.sequence.graph.blend_weights`), normalised and stored in 8 bits
    (the largest code 255; all zero means uniform, as there)."""
    kk = min(k + 1, len(nodes))
    dist, idx = nearest_nodes(points, nodes, kk)
    d_max = np.maximum(dist[:, -1:], 1e-12)
    w = np.clip(1 - dist[:, :k] / d_max, 0, None) ** 2 if kk > k else np.ones((len(points), k))
    top = w.max(1, keepdims=True)
    codes = np.where(top > 1e-12, np.rint(255 * w / np.where(top > 1e-12, top, 1)), 0)
    return idx[:, :k].astype(np.uint16), codes.astype(np.uint8)


def _kabsch(x: np.ndarray, y: np.ndarray, w: np.ndarray, anchors: np.ndarray,
            nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per node the weighted rigid motion (R, t) with R (x - g) + g + t ~ y over its points."""
    m = len(nodes)
    flat_a, flat_w = anchors.reshape(-1), w.reshape(-1).astype(np.float64)
    xs = np.repeat(x.astype(np.float64), anchors.shape[1], 0)
    ys = np.repeat(y.astype(np.float64), anchors.shape[1], 0)
    sw = np.bincount(flat_a, flat_w, m)
    safe = np.where(sw > 0, sw, 1)[:, None]
    cx = np.stack([np.bincount(flat_a, flat_w * xs[:, c], m) for c in range(3)], 1) / safe
    cy = np.stack([np.bincount(flat_a, flat_w * ys[:, c], m) for c in range(3)], 1) / safe
    dx, dy = xs - cx[flat_a], ys - cy[flat_a]
    H = np.zeros((m, 3, 3))
    for a in range(3):
        for b in range(3):
            H[:, a, b] = np.bincount(flat_a, flat_w * dx[:, a] * dy[:, b], m)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.transpose(Vt, (0, 2, 1)) @ np.transpose(U, (0, 2, 1))))
    D = np.zeros((m, 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1
    D[:, 2, 2] = np.where(d == 0, 1, d)
    R = np.transpose(Vt, (0, 2, 1)) @ D @ np.transpose(U, (0, 2, 1))
    R[sw <= 0] = np.eye(3)
    t = cy - np.einsum("mij,mj->mi", R, cx) + np.einsum("mij,mj->mi", R, nodes) - nodes
    t[sw <= 0] = 0
    return R, t


def fit_node_transforms(x: np.ndarray, y: np.ndarray, anchors: np.ndarray, weights: np.ndarray,
                        nodes: np.ndarray, *, joint: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Node quaternions (M, 4) and translations (M, 3) carrying key-space points `x` (N, 3)
    to `y` (N, 3) through the blend (`anchors`, `weights` (N, 4)); `joint` re-solves the
    translations for the blended prediction (damped towards the per-node fits)."""
    R, t = _kabsch(x, y, weights, anchors, nodes)
    q = rotmat_to_quat(R).astype(np.float32)
    if joint and len(x):
        Rq = quat_to_rotmat(q)[anchors]
        g = nodes.astype(np.float64)[anchors]
        base = (weights[..., None] * (np.einsum("nkij,nkj->nki", Rq, x[:, None] - g) + g)).sum(1)
        rows = np.repeat(np.arange(len(x)), anchors.shape[1])
        A = csr_matrix((weights.reshape(-1).astype(np.float64), (rows, anchors.reshape(-1))),
                       shape=(len(x), len(nodes)))
        rhs = y - base - A @ t
        damp = 1e-3
        for c in range(3):
            t[:, c] += lsqr(A, rhs[:, c], damp=damp, atol=1e-10, btol=1e-10, iter_lim=500)[0]
    return q, t.astype(np.float32)
