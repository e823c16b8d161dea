"""One group of pictures of the sequence stream as quantized codes (docs/stream.md), torch-free.

Every attribute is a uniform quantizer with step = its tolerance (`StreamConfig`), so a decoded
value is never further from the frame's own than that tolerance:
- the key frame: codes of every attribute of every Gaussian ("slots"), positions, rotations and
  normals in *key space*; the deformation graph (node positions, each slot's 4 anchor nodes and
  8-bit blend weights);
- each later frame: the graph's node transforms (a unit quaternion and a translation per node,
  `core.sequence.graph` semantics), the slots that died, the slots born (key-space codes and
  anchors, like key entries), and *updates*: for positions, rotations and normals a residual
  code against the graph's prediction from key space, for the other attributes a new code, sent
  only for the slots whose decoded value would otherwise be off by more than the tolerance.

Decoding keeps the codes as state from frame to frame (integers: the page's decoder, which
mirrors `GroupDecoder`, cannot drift from the encoder), deforms key space by the frame's node
transforms and adds the residuals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.export.container import StreamError
from core.export.splats import Splats, dequantize, quantize
from core.rotations import quat_to_rotmat

__all__ = ["ATTRIBUTES", "GroupDecoder", "StreamConfig", "attribute", "blend_deform",
           "blend_parts", "group_quant", "with_attributes", "with_residuals"]

PREDICTED = ("means", "quats", "normals")
DIRECT = ("scales", "opacity", "sh0", "shN", "visibility")
ATTRIBUTES = PREDICTED + DIRECT


@dataclass(frozen=True)
class StreamConfig:
    """Tolerances of the sequence stream: the largest error of a decoded value (the quantizer's
    step; a value is re-sent when its decoded one drifts further than this)."""

    position: float = 1e-4
    """Centres: the quantizer's step as a fraction of the group's bounding-box diagonal, and
    the tolerance where the capture's cameras are not known."""
    position_pixels: float = 0.15
    """Centres, where the cameras are known: the tolerance in pixels of the finest capture
    camera that sees the Gaussian (what the capture could resolve there), at least the step."""
    rotation: float = 0.02
    """Unit-quaternion components (about 2.3 degrees): the step, and the tolerance of a
    strongly anisotropic Gaussian."""
    rotation_max: float = 0.05
    """Unit-quaternion components: the tolerance of a nearly round Gaussian, whose rotation
    barely shows (a slot's tolerance is what moves its surface by the centres' tolerance:
    that over twice its largest minus smallest scale, between `rotation` and this)."""
    normal: float = 0.02
    """Unit-normal components (about 1.1 degrees)."""
    scale: float = 0.05
    """Log-scales (5%)."""
    opacity: float = 0.01
    """Both opacities, activated (0..1)."""
    color: float = 0.05
    """SH degree-0 coefficients (x 0.28 in colour: 3.6/255)."""
    sh: float = 0.05
    """Higher SH coefficients."""
    visibility: float = 0.01
    """Ambient visibility, activated."""
    nodes: int = 1024
    """Most deformation-graph nodes per group."""
    gaussians_per_node: int = 32
    """Graph nodes: one per this many key-frame Gaussians (at least 5, at most `nodes`)."""

    def __post_init__(self) -> None:
        for name in ("position", "position_pixels", "rotation", "rotation_max", "normal",
                     "scale", "opacity", "color", "sh", "visibility"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 < value < 1):
                raise ValueError(f"{name}: expected a tolerance in (0, 1), got {value!r}")
        if self.nodes < 5 or self.gaussians_per_node < 1:
            raise ValueError(f"nodes, gaussians_per_node: expected >= 5 and >= 1, got "
                             f"{self.nodes} and {self.gaussians_per_node}")

    def node_count(self, gaussians: int) -> int:
        return max(5, min(self.nodes, gaussians // self.gaussians_per_node, gaussians))


def attribute(s: Splats, name: str, sh_dim: int) -> np.ndarray:
    """(N, C) float32 values of attribute `name` as the codec sees it."""
    n = len(s)
    if name == "opacity":
        return np.stack([s.opacity_c, s.opacity_g], axis=1)
    if name == "visibility":
        return s.visibility.reshape(n, 1)
    if name == "shN":
        return s.shN[:, :sh_dim].reshape(n, sh_dim * 3)
    return getattr(s, name).reshape(n, -1)


def with_attributes(values: dict[str, np.ndarray], ids: np.ndarray, sh_dim: int) -> Splats:
    """Splats from the codec's (N, C) attribute arrays."""
    n = len(ids)
    shN = np.zeros((n, 15, 3), np.float32)
    shN[:, :sh_dim] = values["shN"].reshape(n, sh_dim, 3)
    return Splats(means=values["means"], scales=values["scales"], quats=values["quats"],
                  opacity_c=values["opacity"][:, 0].copy(),
                  opacity_g=values["opacity"][:, 1].copy(),
                  sh0=values["sh0"], shN=shN, normals=values["normals"],
                  visibility=values["visibility"][:, 0].copy(), ids=ids).canonical()


def group_quant(frames: list[Splats], config: StreamConfig, sh_dim: int) -> dict:
    """Each attribute's quantizer {lo, step, bits} over every frame of the group."""
    allv = {name: np.concatenate([attribute(f, name, sh_dim) for f in frames])
            for name in ("means",) + DIRECT}
    lo_m, hi_m = allv["means"].min(0), allv["means"].max(0)
    diag = float(np.linalg.norm(hi_m - lo_m)) or 1.0
    pad = 0.25 * (hi_m - lo_m) + 0.05 * diag  # born Gaussians' key-space centres stray
    tol = {"means": config.position * diag, "quats": config.rotation, "normals": config.normal,
           "scales": config.scale, "opacity": config.opacity, "sh0": config.color,
           "shN": config.sh, "visibility": config.visibility}
    quant = {}
    for name in ATTRIBUTES:
        if name == "means":
            lo, hi = lo_m - pad, hi_m + pad
        elif name in ("quats", "normals"):
            lo, hi = np.float32(-1.0), np.float32(1.0)
        else:
            v = allv[name]
            lo, hi = (v.min(), v.max()) if v.size else (0.0, 1.0)
        span = float(np.max(np.asarray(hi) - np.asarray(lo)))
        step = max(tol[name], span / 65534)  # codes fit 16 bits, the grid's shift below too
        if name in DIRECT:
            # The grid on multiples of the step (0 a code's centre), not on the group's minimum:
            # values within half a step of 0 (most higher SH) share one code wherever the
            # minimum falls; on the minimum, a shift of 0.01 split that noise into two codes,
            # 15 kB of a 6-frame group's key frame (docs/decisions/2026-11-29-stream-size-held.md).
            lo = np.floor(np.float64(lo) / step) * step
            span = float(np.max(np.asarray(hi) - lo))
        bits = max(1, math.ceil(math.log2(span / step + 1)))
        quant[name] = {"lo": np.atleast_1d(np.float32(lo)).tolist(), "step": float(np.float32(step)),
                       "tol": float(tol[name]), "bits": int(bits)}
    return quant


def codes_of(values: np.ndarray, q: dict) -> np.ndarray:
    return quantize(values, np.float32(q["lo"]), np.float32(q["step"]), q["bits"])


def values_of(codes: np.ndarray, q: dict) -> np.ndarray:
    return dequantize(codes, np.float32(q["lo"]), np.float32(q["step"]))


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.sqrt((v * v).sum(-1, keepdims=True))
    return (v / np.where(n > 0, n, 1)).astype(np.float32)


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw],
                    axis=-1).astype(np.float32)


def weights_of(codes: np.ndarray) -> np.ndarray:
    """(S, 4) blend weights from their 8-bit codes: code / sum (uniform when all are 0)."""
    c = codes.astype(np.float32)
    total = c.sum(1, keepdims=True)
    return np.where(total > 0, c / np.where(total > 0, total, 1), np.float32(0.25))


def blend_parts(anchors: np.ndarray, weights: np.ndarray, nodes: np.ndarray,
                node_q: np.ndarray, node_t: np.ndarray):
    """Per slot the blended deformation x -> A x + c and rotation q_b (unit) of the node
    transforms: sum_j w_j (R_j (x - g_j) + g_j + t_j) = (sum w R) x + sum w (g + t - R g)."""
    R = quat_to_rotmat(node_q).astype(np.float32)[anchors]  # (S, 4, 3, 3)
    g = nodes[anchors]
    w = weights[..., None]
    A = (w[..., None] * R).sum(1)
    c = (w * (g + node_t[anchors] - np.einsum("skij,skj->ski", R, g))).sum(1)
    qb = _unit((w * node_q[anchors]).sum(1))
    return A.astype(np.float32), c.astype(np.float32), qb


def with_residuals(key: dict[str, np.ndarray], res: dict[str, np.ndarray], quant: dict):
    """Key-space values plus their residual codes (the residuals live in key space, so an
    offset from the graph moves and turns with the body instead of being re-sent)."""
    step = {name: np.float32(quant[name]["tol"]) for name in PREDICTED}
    return {"means": key["means"] + res["means"].astype(np.float32) * step["means"],
            "quats": _unit(key["quats"] + res["quats"].astype(np.float32) * step["quats"]),
            "normals": _unit(key["normals"] + res["normals"].astype(np.float32) * step["normals"])}


def blend_deform(local: dict[str, np.ndarray], parts):
    """(means, quats, normals) of key-space values under `blend_parts` (None: the rest pose),
    as `core.sequence.graph.DeformationGraph.deform` computes them."""
    if parts is None:
        return local["means"], local["quats"], local["normals"]
    A, c, qb = parts
    means = np.einsum("sij,sj->si", A, local["means"]) + c
    quats = qmul(qb, local["quats"])
    normals = np.einsum("sij,sj->si", quat_to_rotmat(qb).astype(np.float32),
                        local["normals"])
    return means.astype(np.float32), quats, normals.astype(np.float32)


class GroupDecoder:
    """Decodes one group frame by frame from its payload (`core.export.container.Payload`)."""

    def __init__(self, payload, quant: dict, sh_dim: int, nodes: np.ndarray,
                 codes: dict[str, np.ndarray], anchors: np.ndarray, wcodes: np.ndarray,
                 ids: np.ndarray) -> None:
        self.p, self.quant, self.sh_dim = payload, quant, int(sh_dim)
        self.nodes = nodes.astype(np.float32)
        self.codes = {name: codes[name].astype(np.int64) for name in ATTRIBUTES}
        self.res = {name: np.zeros_like(self.codes[name]) for name in PREDICTED}
        self.anchors, self.wcodes = anchors.astype(np.int64), wcodes
        self.ids = ids.astype(np.int64)
        self.alive = np.ones(len(self.ids), bool)
        self.index = -1

    @classmethod
    def from_payload(cls, payload) -> GroupDecoder:
        meta = payload.meta
        return cls(payload, meta["quant"], meta["sh_dim"], payload.get("graph.nodes"),
                   {name: payload.get(f"key.{name}") for name in ATTRIBUTES},
                   payload.get("key.anchors"), payload.get("key.weights"),
                   payload.get("key.ids"))

    def _births(self, prefix: str) -> None:
        p = self.p
        count = int(p.meta["frame_meta"][self.index]["births"])
        if not count:
            return
        for name in ATTRIBUTES:
            self.codes[name] = np.concatenate([self.codes[name],
                                               p.get(f"{prefix}.born.{name}").astype(np.int64)])
        for name in PREDICTED:
            self.res[name] = np.concatenate([self.res[name],
                                             np.zeros((count, self.res[name].shape[1]), np.int64)])
        self.anchors = np.concatenate([self.anchors, p.get(f"{prefix}.born.anchors")])
        self.wcodes = np.concatenate([self.wcodes, p.get(f"{prefix}.born.weights")])
        self.ids = np.concatenate([self.ids, p.get(f"{prefix}.born.ids").astype(np.int64)])
        self.alive = np.concatenate([self.alive, np.ones(count, bool)])

    def _updates(self, prefix: str) -> None:
        for name in ATTRIBUTES:
            key = f"{prefix}.upd.{name}"
            if f"{key}.idx" not in self.p.arrays:
                continue
            idx = np.cumsum(self.p.get(f"{key}.idx").astype(np.int64))
            target = self.res if name in PREDICTED else self.codes
            if idx.size and (idx.max() >= len(self.ids)):
                raise StreamError(f"group {self.p.meta['group']}: an update names slot "
                                  f"{int(idx.max())} of {len(self.ids)}")
            target[name][idx] += self.p.get(f"{key}.val").astype(np.int64)  # deltas

    def frame(self) -> Splats:
        """The next frame of the group."""
        self.index += 1
        prefix = f"f{self.index}"
        node_q = node_t = None
        if self.index > 0:
            dead = np.cumsum(self.p.get(f"{prefix}.deaths").astype(np.int64))
            self.alive[dead] = False
            self._births(prefix)
            node_q = self.p.get(f"{prefix}.node_q").astype(np.float32)
            node_t = self.p.get(f"{prefix}.node_t").astype(np.float32)
        self._updates(prefix)
        return self.splats(node_q, node_t)

    def key_values(self) -> dict[str, np.ndarray]:
        out = {name: values_of(self.codes[name], self.quant[name]) for name in ATTRIBUTES}
        out["quats"], out["normals"] = _unit(out["quats"]), _unit(out["normals"])
        return out

    def parts(self, node_q, node_t):
        """`blend_parts` of every slot (None for the key frame)."""
        if node_q is None:
            return None
        return blend_parts(self.anchors, weights_of(self.wcodes), self.nodes, node_q, node_t)

    def splats(self, node_q, node_t) -> Splats:
        v = self.key_values()
        local = with_residuals(v, self.res, self.quant)
        v["means"], v["quats"], v["normals"] = blend_deform(local, self.parts(node_q, node_t))
        a = self.alive
        return with_attributes({k: x[a] for k, x in v.items()}, self.ids[a], self.sh_dim)
