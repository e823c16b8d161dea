"""The embedded deformation graph (Sumner, Schmid and Pauly 2007, "Embedded deformation for shape
manipulation") over a frame's Gaussians, as docs/design.md section 5 fixes it:

- nodes: farthest-point samples of the Gaussian centres (default 1024);
- each Gaussian blends its 4 nearest nodes with weights (1 - d/d_max)^2, d_max the distance to the
  5th nearest node, normalised to sum 1 (Sumner et al. eq. 3);
- each node j carries a rotation (an unnormalised quaternion p_j, w x y z) and a translation t_j;
  a point moves to sum_j w_j (R_j (x - g_j) + g_j + t_j) with R_j the rotation of p_j / |p_j|;
- orientations (Gaussian quaternions and normals) turn by the blend of the node quaternions,
  q_b = normalise(sum_j w_j p_j): Gaussians get q_b * q, normals R(q_b) n. The blend uses the
  unnormalised p_j, which is why the deform stage keeps them at unit norm (`quat_norm_loss`).
- regularisation: ARAP over node neighbours (Sumner et al. E_reg),
  sum over edges (j, l) of |R_j (g_l - g_j) + g_j + t_j - (g_l + t_l)|^2.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import torch
from torch import Tensor

__all__ = ["DeformationGraph", "arap_loss", "blend_weights", "build_graph",
           "farthest_point_sampling", "quat_multiply", "quat_norm_loss", "quat_to_rotmat"]


def farthest_point_sampling(points: Tensor, count: int, start: int = 0) -> Tensor:
    """(count,) distinct indices into `points` (N, 3): `start` first, then each next the point
    farthest from those chosen (deterministic; ties take the lowest index, so points at the
    same place come in index order)."""
    if points.dim() != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise ValueError(f"points: expected shape (N, 3) with N > 0, got {tuple(points.shape)}")
    n = points.shape[0]
    if not 1 <= count <= n:
        raise ValueError(f"count: expected 1..{n} (the number of points), got {count}")
    pts = points.detach()
    chosen = torch.empty(count, dtype=torch.long, device=pts.device)
    chosen[0] = start
    dist = (pts - pts[start]).square().sum(dim=1)
    dist[start] = -1.0  # never chosen twice, also where points coincide
    for i in range(1, count):
        # The index stays a device tensor: no read-back a node (1,024 a tracked frame).
        nxt = dist.argmax()
        chosen[i] = nxt
        # A chosen point keeps -1 (its distances are >= 0); the new one is marked.
        dist = torch.minimum(dist, (pts - pts[nxt]).square().sum(dim=1))
        dist[nxt] = -1.0
    return chosen


def blend_weights(dist: Tensor) -> Tensor:
    """(N, K) weights from (N, K+1) ascending distances to the K+1 nearest nodes:
    (1 - d_k / d_{K+1})^2 normalised to sum 1; a row whose weights all vanish (its K nearest
    nodes as far as the next one) gets uniform weights."""
    if dist.dim() != 2 or dist.shape[1] < 2:
        raise ValueError(f"dist: expected shape (N, K+1) with K >= 1, got {tuple(dist.shape)}")
    d_max = dist[:, -1:].clamp_min(1e-12)
    w = (1 - dist[:, :-1] / d_max).clamp_min(0).square()
    total = w.sum(dim=1, keepdim=True)
    uniform = torch.full_like(w, 1.0 / w.shape[1])
    return torch.where(total > 1e-12, w / total.clamp_min(1e-12), uniform)


def _knn(queries: Tensor, points: Tensor, k: int, chunk: int = 4096) -> tuple[Tensor, Tensor]:
    """(distances, indices) of the k nearest `points` to each query, ascending."""
    dists, idx = [], []
    for s in range(0, queries.shape[0], chunk):
        d = torch.cdist(queries[s:s + chunk], points)
        v, i = d.topk(k, dim=1, largest=False)
        dists.append(v)
        idx.append(i)
    return torch.cat(dists), torch.cat(idx)


# Both quaternion maps a deform step calls are quadratic in quaternion components, so each is
# one outer product and one matrix product with a constant table: a handful of operators forward
# and back where the entries written out one by one took 140 (rotation) and 67 (product), each a
# kernel launch on a GPU (docs/benchmarks.md, "A step's host syncs"). Tables are (16, K): row
# 4 i + j holds the coefficient of u_i v_j in each of the K outputs.
_HAMILTON = (  # (a * b)_k = sum over (i, j, sign) of sign a_i b_j, components w x y z
    ((0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, -1)),
    ((0, 1, 1), (1, 0, 1), (2, 3, 1), (3, 2, -1)),
    ((0, 2, 1), (1, 3, -1), (2, 0, 1), (3, 1, 1)),
    ((0, 3, 1), (1, 2, 1), (2, 1, -1), (3, 0, 1)),
)
_ROTATION = (  # R(u) of a unit quaternion, row-major: u^T A_k u with A_k symmetric
    ((0, 0, 1), (1, 1, 1), (2, 2, -1), (3, 3, -1)),  # w w + x x - y y - z z = 1 - 2 (yy + zz)
    ((1, 2, 2), (0, 3, -2)), ((1, 3, 2), (0, 2, 2)),
    ((1, 2, 2), (0, 3, 2)),
    ((0, 0, 1), (1, 1, -1), (2, 2, 1), (3, 3, -1)),
    ((2, 3, 2), (0, 1, -2)),
    ((1, 3, 2), (0, 2, -2)), ((2, 3, 2), (0, 1, 2)),
    ((0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, 1)),
)


@cache
def _table(name: str, device: torch.device, dtype: torch.dtype) -> Tensor:
    """The (16, K) table on `device` (made there once: no copy from the host a step)."""
    terms = {"hamilton": _HAMILTON, "rotation": _ROTATION}[name]
    table = torch.zeros(16, len(terms), dtype=torch.float64)
    for k, output in enumerate(terms):
        for i, j, c in output:
            if i == j or name == "hamilton":
                table[4 * i + j, k] += c
            else:  # a symmetric form: the cross term's coefficient split over both orders
                table[4 * i + j, k] += c / 2
                table[4 * j + i, k] += c / 2
    return table.to(device=device, dtype=dtype)


def _bilinear(name: str, u: Tensor, v: Tensor) -> Tensor:
    outer = (u[..., :, None] * v[..., None, :]).flatten(-2)
    return outer @ _table(name, u.device, u.dtype)


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b of (..., 4) quaternions (w, x, y, z)."""
    a, b = torch.broadcast_tensors(a, b)
    return _bilinear("hamilton", a, b)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """(N, 4) quaternions (w, x, y, z), any norm -> (N, 3, 3) rotation matrices:
    `native.reference.quat_to_rotmat` (a test holds them equal, values and gradients) in a
    few operators."""
    u = quats / quats.norm(dim=-1, keepdim=True)
    return _bilinear("rotation", u, u).reshape(-1, 3, 3)


@dataclass(frozen=True)
class DeformationGraph:
    """Nodes and the per-Gaussian blending of one frame's Gaussians."""

    nodes: Tensor
    """(M, 3) node positions g_j (farthest-point samples of the Gaussian centres)."""
    anchors: Tensor
    """(N, K) int64: the K nearest nodes of each Gaussian."""
    weights: Tensor
    """(N, K) blending weights, rows sum to 1."""
    edges: Tensor
    """(E, 2) int64 node pairs (j, l): l is among j's nearest nodes (ARAP neighbours)."""

    def __len__(self) -> int:
        return self.nodes.shape[0]

    def identity(self) -> tuple[Tensor, Tensor]:
        """Node parameters of the rest state: quaternions (M, 4) = (1, 0, 0, 0), translations
        (M, 3) = 0."""
        dev = self.nodes.device
        q = torch.zeros(len(self), 4, device=dev)
        q[:, 0] = 1.0
        return q, torch.zeros(len(self), 3, device=dev)

    def _check(self, rotations: Tensor, translations: Tensor) -> None:
        m = len(self)
        if tuple(rotations.shape) != (m, 4) or tuple(translations.shape) != (m, 3):
            raise ValueError(f"rotations, translations: expected shapes ({m}, 4) and ({m}, 3), "
                             f"got {tuple(rotations.shape)} and {tuple(translations.shape)}")

    def deform_points(self, points: Tensor, rotations: Tensor, translations: Tensor) -> Tensor:
        """(N, 3): sum_j w_j (R_j (x - g_j) + g_j + t_j) over each point's anchor nodes."""
        self._check(rotations, translations)
        R = quat_to_rotmat(rotations)[self.anchors]  # (N, K, 3, 3)
        g = self.nodes[self.anchors]  # (N, K, 3)
        local = torch.einsum("nkij,nkj->nki", R, points[:, None, :] - g)
        moved = local + g + translations[self.anchors]
        return (self.weights[..., None] * moved).sum(dim=1)

    def blend_rotation(self, rotations: Tensor) -> Tensor:
        """(N, 4) unit quaternions q_b = normalise(sum_j w_j p_j)."""
        q = (self.weights[..., None] * rotations[self.anchors]).sum(dim=1)
        return torch.nn.functional.normalize(q, dim=-1)

    def deform(self, means: Tensor, quats: Tensor, normals: Tensor, rotations: Tensor,
               translations: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Deformed (means, quats, normals): positions by the blended node transforms, Gaussian
        quaternions (any norm, w x y z) left-multiplied by q_b, normals rotated by R(q_b)
        (their length kept)."""
        qb = self.blend_rotation(rotations)
        new_means = self.deform_points(means, rotations, translations)
        new_quats = quat_multiply(qb, quats)
        new_normals = torch.einsum("nij,nj->ni", quat_to_rotmat(qb), normals)
        return new_means, new_quats, new_normals

    def moved_nodes(self, translations: Tensor) -> Tensor:
        """(M, 3) node positions after the deformation, g_j + t_j."""
        return self.nodes + translations


def build_graph(points: Tensor, num_nodes: int = 1024, k: int = 4,
                node_neighbors: int = 8) -> DeformationGraph:
    """The graph of `points` (N, 3): min(num_nodes, N) farthest-point nodes, each point blended
    from its `k` nearest nodes (d_max: the (k+1)-th), ARAP edges to each node's
    `node_neighbors` nearest other nodes. Needs at least k + 1 nodes."""
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {tuple(points.shape)}")
    m = min(num_nodes, points.shape[0])
    if m < k + 1:
        raise ValueError(f"points: a graph blending {k} nodes needs at least {k + 1} nodes; got "
                         f"{points.shape[0]} points and num_nodes={num_nodes}")
    pts = points.detach().float()
    nodes = pts[farthest_point_sampling(pts, m)]
    dist, idx = _knn(pts, nodes, k + 1)
    nn = min(node_neighbors, m - 1)
    _, nidx = _knn(nodes, nodes, nn + 1)
    src = torch.arange(m, device=pts.device)[:, None].expand(m, nn)
    edges = torch.stack([src.reshape(-1), nidx[:, 1:].reshape(-1)], dim=1)
    return DeformationGraph(nodes=nodes, anchors=idx[:, :k].contiguous(),
                            weights=blend_weights(dist), edges=edges)


def arap_loss(graph: DeformationGraph, rotations: Tensor, translations: Tensor) -> Tensor:
    """Mean over edges (j, l) of |R_j (g_l - g_j) + g_j + t_j - (g_l + t_l)|^2, divided by the
    mean squared edge length so the weight does not depend on the scene's scale."""
    j, l = graph.edges[:, 0], graph.edges[:, 1]
    g = graph.nodes
    R = quat_to_rotmat(rotations)[j]
    d = g[l] - g[j]
    pred = torch.einsum("eab,eb->ea", R, d) + g[j] + translations[j]
    r = pred - (g[l] + translations[l])
    return r.square().sum(dim=1).mean() / d.square().sum(dim=1).mean().clamp_min(1e-12)


def quat_norm_loss(rotations: Tensor) -> Tensor:
    """Mean of (|p_j| - 1)^2 over the node quaternions."""
    return (rotations.norm(dim=1) - 1).square().mean()
