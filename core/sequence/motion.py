"""Motion prediction for the deform stage: the graph's node transforms start where the previous
frame's motion would carry them, not at rest.

Each node's rigid motion from frame t-2 to t-1 is fitted to the Gaussians it carries (weighted
Kabsch/Umeyama without scale, over the Gaussians whose track ids exist in both frames) and
applied again, scaled by a damping factor a: the rotation angle times a, the node centre moved by
a times its fitted displacement. A constant-velocity guess (a = 1) overshoots where a limb
reverses; a = cos(w) is the best linear two-frame predictor of a swing of w radians per frame
(its error is sin(w) of the zero-motion guess's, against 2 sin(w/2) for a = 1).

With three frames of history a second-order prediction is possible: each Gaussian's next
displacement 2c d_t - d_{t-1}, exact for a sinusoid of w radians a frame with c = cos(w)
(c = 1: constant acceleration), then per node the rigid motion that carries its Gaussians
there. Unlike a damping it turns a limb around at the end of its swing.
"""

from __future__ import annotations

import torch
from torch import Tensor

from core.sequence.graph import DeformationGraph

__all__ = ["align_tracks", "predict_node_motion", "predict_node_motion_second_order"]


def align_tracks(ids: Tensor, earlier_ids: Tensor, earlier_means: Tensor) -> tuple[Tensor, Tensor]:
    """(earlier positions (N, 3), known (N,) bool) of the Gaussians with track ids `ids` (N,),
    looked up among an earlier frame's (`earlier_ids` (M,), `earlier_means` (M, 3)); Gaussians
    born since then are not known (position 0)."""
    dev = earlier_means.device
    ids, earlier_ids = ids.to(dev), earlier_ids.to(dev)
    if earlier_ids.numel() == 0 or ids.numel() == 0:
        return (torch.zeros(len(ids), 3, device=dev),
                torch.zeros(len(ids), dtype=torch.bool, device=dev))
    size = int(max(int(ids.max()), int(earlier_ids.max()))) + 1
    where = torch.full((size,), -1, dtype=torch.long, device=dev)
    where[earlier_ids.long()] = torch.arange(len(earlier_ids), device=dev)
    index = where[ids.long()]
    known = index >= 0
    positions = torch.zeros(len(ids), 3, dtype=earlier_means.dtype, device=dev)
    positions[known] = earlier_means[index[known]]
    return positions, known


def _rotmat_to_axis_angle(R: Tensor) -> Tensor:
    """(M, 3) axis * angle of rotation matrices (M, 3, 3), angles in [0, pi)."""
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1.0, 1.0)
    angle = torch.arccos(cos)
    axis = torch.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0],
                        R[:, 1, 0] - R[:, 0, 1]], dim=-1)
    norm = axis.norm(dim=-1, keepdim=True)
    return torch.where(norm > 1e-8, axis / norm.clamp_min(1e-8) * angle[:, None],
                       torch.zeros_like(axis))


def _axis_angle_to_quat(v: Tensor) -> Tensor:
    """(M, 4) unit quaternions (w, x, y, z) of axis-angle vectors (M, 3)."""
    angle = v.norm(dim=-1, keepdim=True)
    axis = v / angle.clamp_min(1e-12)
    return torch.cat([torch.cos(angle / 2), axis * torch.sin(angle / 2)], dim=-1)


def _fit_node_rigid(graph: DeformationGraph, src: Tensor, dst: Tensor, known: Tensor,
                    min_points: int) -> tuple[Tensor, Tensor, Tensor]:
    """Per node, the rigid motion (no scale) that best carries `src` onto `dst` (both (N, 3), the
    graph's Gaussians; `known` (N,) marks those to use), weighted by the blend weights (weighted
    Kabsch/Umeyama, dst ~ R (src - mu_src) + mu_dst): (R (M, 3, 3), the node centre's
    displacement under it R (g - mu_src) + mu_dst - g (M, 3), ok (M,)) in float64; ok is False
    for a node carrying fewer than `min_points` known Gaussians."""
    m, dev = len(graph), graph.nodes.device
    # Sums over each node's (Gaussian, weight) pairs, scattered from the K anchors of each
    # Gaussian (never an (N, M) matrix: real frames have 1e5-1e6 Gaussians and 1024 nodes).
    w = (graph.weights * known[:, None].to(graph.weights)).double().reshape(-1)  # (N K,)
    nodes = graph.anchors.reshape(-1)
    k = graph.anchors.shape[1]
    p = src.double().repeat_interleave(k, dim=0)  # (N K, 3)
    c = dst.double().repeat_interleave(k, dim=0)
    total = torch.zeros(m, dtype=torch.float64, device=dev).index_add_(0, nodes, w)
    count = torch.zeros(m, dtype=torch.float64, device=dev).index_add_(0, nodes, (w > 0).double())
    ok = (count >= min_points) & (total > 1e-8)
    total = total.clamp_min(1e-12)
    zeros = torch.zeros(m, 3, dtype=torch.float64, device=dev)
    mu_p = zeros.index_add(0, nodes, w[:, None] * p) / total[:, None]
    mu_c = zeros.index_add(0, nodes, w[:, None] * c) / total[:, None]
    # Weighted cross-covariance of each node: sum_i w_ij (c_i - mu_c_j)(p_i - mu_p_j)^T.
    outer = (w[:, None, None] * c[:, :, None] * p[:, None, :]).reshape(-1, 9)
    sums = torch.zeros(m, 9, dtype=torch.float64, device=dev).index_add_(0, nodes, outer)
    cov = sums.reshape(m, 3, 3) - total[:, None, None] * mu_c[:, :, None] * mu_p[:, None, :]
    U, _, Vh = torch.linalg.svd(cov)
    d = torch.sign(torch.linalg.det(U @ Vh))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
    R = U @ D @ Vh
    g = graph.nodes.double()
    return R, torch.einsum("mab,mb->ma", R, g - mu_p) + mu_c - g, ok


def predict_node_motion(graph: DeformationGraph, current: Tensor, earlier: Tensor, known: Tensor,
                        damping: float, min_points: int = 4) -> tuple[Tensor, Tensor]:
    """Node (quaternions (M, 4), translations (M, 3)) that continue the motion `earlier` ->
    `current` (both (N, 3), the graph's Gaussians at frames t-2 and t-1; `known` (N,) marks those
    present in both), scaled by `damping`. A node that carries fewer than `min_points` known
    Gaussians (or a non-positive damping) gets the identity."""
    q, t = graph.identity()
    if damping <= 0 or not bool(known.any()):
        return q, t
    R, step, ok = _fit_node_rigid(graph, earlier, current, known, min_points)
    # The motion t-2 -> t-1 applied to the node centre once more, scaled by the damping; the
    # rotation about the node by the damped angle.
    step_q = _axis_angle_to_quat(damping * _rotmat_to_axis_angle(R)).float()
    step_t = (damping * step).float()
    q[ok], t[ok] = step_q[ok], step_t[ok]
    return q, t


def predict_node_motion_second_order(graph: DeformationGraph, current: Tensor, earlier: Tensor,
                                     earliest: Tensor, known: Tensor, c: float,
                                     min_points: int = 4) -> tuple[Tensor, Tensor]:
    """Node (quaternions (M, 4), translations (M, 3)) from a second-order prediction of the
    graph's Gaussians at frames t-3, t-2, t-1 (`earliest`, `earlier`, `current`, (N, 3);
    `known` (N,) marks those present in all three): each Gaussian's next displacement is
    2c d_{t-1} - d_{t-2} (d: its displacement over a frame), the recurrence that any sinusoid
    of w radians a frame with cos(w) = c satisfies exactly (c = 1: constant acceleration), and
    each node gets the rigid motion that best carries its Gaussians there. A node carrying
    fewer than `min_points` known Gaussians gets the identity."""
    if not -1.0 <= c <= 1.0:
        raise ValueError(f"c: expected cos(w) in [-1, 1], got {c}")
    q, t = graph.identity()
    if not bool(known.any()):
        return q, t
    x1, x2, x3 = current.double(), earlier.double(), earliest.double()
    target = x1 + 2 * c * (x1 - x2) - (x2 - x3)
    R, step, ok = _fit_node_rigid(graph, x1, target, known, min_points)
    step_q = _axis_angle_to_quat(_rotmat_to_axis_angle(R)).float()
    q[ok], t[ok] = step_q[ok], step.float()[ok]
    return q, t
