"""Encoding one group of pictures into its stream chunk's payload (the inverse of
`core.export.codec.GroupDecoder`, which it runs alongside so that every decision is taken
against what the decoder will hold)."""

from __future__ import annotations

import numpy as np

from core.export.codec import (
    ATTRIBUTES,
    PREDICTED,
    GroupDecoder,
    StreamConfig,
    _unit,
    attribute,
    blend_deform,
    codes_of,
    group_quant,
    qmul,
    values_of,
    weights_of,
    with_residuals,
)
from core.export.graphfit import (
    anchor_weights,
    fit_node_transforms,
    graph_nodes,
    nearest_nodes,
)
from core.export.splats import Splats
from core.rotations import quat_to_rotmat

__all__ = ["encode_group"]

_I16 = 32767


def pixel_footprint(points: np.ndarray, cameras: list[dict]) -> np.ndarray | None:
    """(N,) the size of a pixel at each point for the finest capture camera that sees it
    (depth / focal length; cameras where it projects into the image, in front), None without
    cameras; points no camera sees get the median of the others."""
    if not cameras or not len(points):
        return None
    best = np.full(len(points), np.inf)
    for c in cameras:
        m = np.asarray(c["world_to_camera"], np.float64)
        K = np.asarray(c["K"], np.float64)
        p = points.astype(np.float64) @ m[:3, :3].T + m[:3, 3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = K[0, 0] * p[:, 0] / z + K[0, 2], K[1, 1] * p[:, 1] / z + K[1, 2]
        seen = (z > 0.01) & (u >= 0) & (u <= c["width"]) & (v >= 0) & (v <= c["height"])
        best = np.where(seen, np.minimum(best, z / max(K[0, 0], K[1, 1])), best)
    finite = np.isfinite(best)
    if not finite.any():
        return None
    return np.where(finite, best, np.median(best[finite]))


def _narrow(deltas: np.ndarray) -> np.ndarray:
    """Integer deltas in the narrowest of int8, int16, int32 that holds them."""
    top = int(np.abs(deltas).max()) if deltas.size else 0
    return deltas.astype(np.int8 if top <= 127 else np.int16 if top <= _I16 else np.int32)


def _delta(idx: np.ndarray) -> np.ndarray:
    """Sorted slot indices as first differences (what deflate compresses best)."""
    return np.diff(np.asarray(idx, np.int64), prepend=0).astype(np.uint32)


class _Encoder:
    def __init__(self, frames: list[Splats], config: StreamConfig, sh_dim: int, group: int,
                 cameras: list[dict] | None = None):
        self.frames, self.config, self.sh_dim = frames, config, sh_dim
        self.cameras = cameras or []
        self.quant = group_quant(frames, config, sh_dim)
        key = frames[0]
        self.arrays: dict[str, np.ndarray] = {}
        self.meta = {"group": group, "sh_dim": sh_dim, "quant": self.quant, "frame_meta": []}
        codes = {name: codes_of(attribute(key, name, sh_dim), self.quant[name])
                 for name in ATTRIBUTES}
        # The graph lives in decoded key space, so the decoder computes what the encoder did.
        key_means = self._values("means", codes["means"])
        self.nodes = graph_nodes(key_means, config.node_count(len(key)))
        anchors, wcodes = anchor_weights(key_means, self.nodes)
        self.arrays.update({f"key.{n}": c for n, c in codes.items()})
        self.arrays.update({"key.anchors": anchors, "key.weights": wcodes,
                            "key.ids": key.ids.astype(np.uint32), "graph.nodes": self.nodes})
        self.decoder = GroupDecoder(None, self.quant, sh_dim, self.nodes, codes, anchors, wcodes,
                                    key.ids)
        self.position_tol = self._position_tol(key_means)
        """Per slot: how far its decoded centre may be from the frame's (encoder only)."""

    def _position_tol(self, points: np.ndarray) -> np.ndarray:
        step = self.quant["means"]["tol"]
        foot = pixel_footprint(points, self.cameras)
        if foot is None:
            return np.full(len(points), step, np.float32)
        return np.maximum(step, self.config.position_pixels * foot).astype(np.float32)

    def _values(self, name: str, codes: np.ndarray) -> np.ndarray:
        v = values_of(codes, self.quant[name])
        return _unit(v) if name in ("quats", "normals") else v

    # -- one tracked frame --------------------------------------------------------------------
    def _slots(self, frame: Splats) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(slot of each of the frame's Gaussians (-1: born now), dead slots, born rows)."""
        d = self.decoder
        order = np.argsort(d.ids, kind="stable")
        pos = np.searchsorted(d.ids[order], frame.ids)
        pos = np.minimum(pos, len(order) - 1)
        found = d.ids[order][pos] == frame.ids
        slot = np.where(found, order[pos], -1)
        slot = np.where(found & d.alive[np.maximum(slot, 0)], slot, -1)
        present = np.zeros(len(d.ids), bool)
        present[slot[slot >= 0]] = True
        dead = np.flatnonzero(d.alive & ~present)
        return slot, dead, np.flatnonzero(slot < 0)

    def _fit(self, frame: Splats, slot: np.ndarray):
        d = self.decoder
        rows = np.flatnonzero(slot >= 0)
        x = self.decoder.key_values()["means"][slot[rows]]
        q, t = fit_node_transforms(x, frame.means[rows], d.anchors[slot[rows]],
                                   weights_of(d.wcodes[slot[rows]]), self.nodes)
        return q, t

    def _born(self, prefix: str, frame: Splats, rows: np.ndarray, q: np.ndarray, t: np.ndarray):
        """Key-space codes of the Gaussians born in this frame (through their nearest moved
        node's rigid motion) appended as new slots."""
        d = self.decoder
        born = frame.take(rows)
        _, near = nearest_nodes(born.means, self.nodes + t, 1)
        n = near[:, 0]
        Rt = np.transpose(quat_to_rotmat(q[n]).astype(np.float32), (0, 2, 1))
        qc = q[n] * np.float32([1, -1, -1, -1])
        key_space = {
            "means": np.einsum("nij,nj->ni", Rt, born.means - self.nodes[n] - t[n]) + self.nodes[n],
            "quats": qmul(qc, born.quats),
            "normals": np.einsum("nij,nj->ni", Rt, born.normals)}
        codes = {}
        for name in ATTRIBUTES:
            v = key_space[name] if name in PREDICTED else attribute(born, name, self.sh_dim)
            codes[name] = codes_of(v, self.quant[name])
            self.arrays[f"{prefix}.born.{name}"] = codes[name]
        anchors, wcodes = anchor_weights(self._values("means", codes["means"]), self.nodes)
        self.arrays.update({f"{prefix}.born.anchors": anchors, f"{prefix}.born.weights": wcodes,
                            f"{prefix}.born.ids": born.ids.astype(np.uint32)})
        for name in ATTRIBUTES:
            d.codes[name] = np.concatenate([d.codes[name], codes[name].astype(np.int64)])
        for name in PREDICTED:
            d.res[name] = np.concatenate([d.res[name], np.zeros((len(rows), d.res[name].shape[1]),
                                                                np.int64)])
        d.anchors = np.concatenate([d.anchors, anchors.astype(np.int64)])
        d.wcodes = np.concatenate([d.wcodes, wcodes])
        d.ids = np.concatenate([d.ids, born.ids.astype(np.int64)])
        d.alive = np.concatenate([d.alive, np.ones(len(rows), bool)])
        self.position_tol = np.concatenate([self.position_tol, self._position_tol(born.means)])
        return np.arange(len(d.ids) - len(rows), len(d.ids))

    def _rotation_tol(self, frame: Splats, slot: np.ndarray) -> np.ndarray:
        """Per Gaussian: the quaternion error that moves its 1-sigma surface by the centres'
        tolerance (a round Gaussian's rotation does not show)."""
        s = np.exp(frame.scales.astype(np.float64))
        spread = 2 * (s.max(1) - s.min(1))
        tol = self.position_tol[slot] / np.maximum(spread, 1e-12)
        return np.clip(tol, self.config.rotation, self.config.rotation_max)

    def _targets(self, frame: Splats, slot: np.ndarray, parts) -> dict[str, np.ndarray]:
        """The key-space residual codes that would carry each slot exactly to `frame`."""
        d = self.decoder
        kv = {k: v[slot] for k, v in d.key_values().items()}
        step = {name: np.float32(self.quant[name]["tol"]) for name in PREDICTED}
        if parts is None:
            local = {"means": frame.means, "quats": frame.quats, "normals": frame.normals}
        else:
            A, c, qb = (x[slot] for x in parts)
            qc = qb * np.float32([1, -1, -1, -1])
            local = {"means": np.linalg.solve(A.astype(np.float64),
                                              (frame.means - c)[..., None].astype(np.float64))[..., 0],
                     "quats": qmul(qc, frame.quats),
                     "normals": np.einsum("sji,sj->si", quat_to_rotmat(qb).astype(np.float32),
                                          frame.normals)}
        q = local["quats"]  # q and -q: the key's side
        local["quats"] = np.where((q * kv["quats"]).sum(1, keepdims=True) < 0, -q, q)
        return {name: np.clip(np.rint((local[name] - kv[name]) / step[name]), -_I16, _I16)
                .astype(np.int64) for name in PREDICTED}

    def _updates(self, prefix: str, frame: Splats, slot: np.ndarray, q, t) -> dict[str, int]:
        """Re-send what drifted beyond its tolerance; returns how many slots per attribute."""
        d = self.decoder
        parts = d.parts(q, t)
        local = with_residuals({k: v[slot] for k, v in d.key_values().items()},
                               {k: v[slot] for k, v in d.res.items()}, self.quant)
        now = dict(zip(PREDICTED, blend_deform(local, None if parts is None else
                                               tuple(x[slot] for x in parts))))
        targets = self._targets(frame, slot, parts)
        counts = {}
        for name in ATTRIBUTES:
            qd = self.quant[name]
            actual = attribute(frame, name, self.sh_dim)
            if name in PREDICTED:
                cur = now[name]
                if name == "quats":  # q and -q are one rotation
                    actual = np.where((actual * cur).sum(1, keepdims=True) < 0, -actual, actual)
                codes, state = targets[name], d.res[name]
            else:
                cur = self._values(name, d.codes[name][slot])
                codes, state = codes_of(actual, qd).astype(np.int64), d.codes[name]
            err = np.abs(actual - cur).max(1)
            tol = self.position_tol[slot] if name == "means" else \
                self._rotation_tol(frame, slot) if name == "quats" else qd["tol"]
            send = np.flatnonzero(err > tol)
            order = send[np.argsort(slot[send], kind="stable")]
            counts[name] = int(len(order))
            if len(order):
                new = codes[order]
                self.arrays[f"{prefix}.upd.{name}.idx"] = _delta(slot[order])
                self.arrays[f"{prefix}.upd.{name}.val"] = _narrow(new - state[slot[order]])
                state[slot[order]] = new
        return counts

    def frame(self, index: int) -> None:
        frame, prefix = self.frames[index], f"f{index}"
        d = self.decoder
        d.index = index
        if index == 0:
            slot = np.arange(len(frame))
            q = t = None
            meta = {"births": 0, "deaths": 0}
        else:
            slot, dead, born_rows = self._slots(frame)
            q, t = self._fit(frame, slot)
            d.alive[dead] = False
            self.arrays[f"{prefix}.deaths"] = _delta(dead)
            self.arrays[f"{prefix}.node_q"] = q
            self.arrays[f"{prefix}.node_t"] = t
            if len(born_rows):
                slot = slot.copy()
                slot[born_rows] = self._born(prefix, frame, born_rows, q, t)
            meta = {"births": int(len(born_rows)), "deaths": int(len(dead))}
        meta["updates"] = self._updates(prefix, frame, slot, q, t)
        meta["gaussians"] = len(frame)
        self.meta["frame_meta"].append(meta)


def encode_group(frames: list[Splats], config: StreamConfig, *, sh_dim: int = 15,
                 group: int = 0, cameras: list[dict] | None = None
                 ) -> tuple[dict, dict[str, np.ndarray]]:
    """(metadata, named arrays) of one group: `frames[0]` is its key frame; the others must
    carry the key frame's track ids for the Gaussians they share with it. `cameras` (the
    stream header's) make the centres' tolerance a fraction of a capture pixel."""
    if not frames:
        raise ValueError("frames: a group needs at least its key frame")
    if sh_dim not in (0, 3, 8, 15):
        raise ValueError(f"sh_dim: expected 0, 3, 8 or 15 (SH degree 0-3), got {sh_dim}")
    for f in frames:
        if len(np.unique(f.ids)) != len(f):
            raise ValueError("frames: a frame repeats a track id; ids must be unique per frame")
    enc = _Encoder(frames, config, sh_dim, group, cameras)
    for i in range(len(frames)):
        enc.frame(i)
    return enc.meta, enc.arrays
