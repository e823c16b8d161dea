"""Encoding one group of pictures into its stream chunk's payload (the inverse of
`core.export.codec.GroupDecoder`, which it runs alongside so that every decision is taken
against what the decoder will hold)."""

from __future__ import annotations

import numpy as np

from core.export.codec import (
    ATTRIBUTES,
    DIRECT,
    PREDICTED,
    GroupDecoder,
    StreamConfig,
    _unit,
    attribute,
    blend_deform,
    codes_of,
    group_quant,
    quat_to_rotmat,
    qmul,
    weights_of,
)
from core.export.graphfit import anchor_weights, fit_node_transforms, graph_nodes, nearest_nodes
from core.export.splats import Splats

__all__ = ["encode_group"]

_I16 = 32767


def _delta(idx: np.ndarray) -> np.ndarray:
    """Sorted slot indices as first differences (what deflate compresses best)."""
    return np.diff(np.asarray(idx, np.int64), prepend=0).astype(np.uint32)


class _Encoder:
    def __init__(self, frames: list[Splats], config: StreamConfig, sh_dim: int, group: int):
        self.frames, self.config, self.sh_dim = frames, config, sh_dim
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

    def _values(self, name: str, codes: np.ndarray) -> np.ndarray:
        from core.export.codec import values_of

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
        Rt = np.transpose(quat_to_rotmat(q[n]), (0, 2, 1))
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
        return np.arange(len(d.ids) - len(rows), len(d.ids))

    def _updates(self, prefix: str, frame: Splats, slot: np.ndarray, q, t) -> dict[str, int]:
        """Re-send what drifted beyond its tolerance; returns how many slots per attribute."""
        d = self.decoder
        kv = d.key_values()
        pred = dict(zip(PREDICTED, blend_deform(kv, d.anchors, weights_of(d.wcodes), self.nodes,
                                                q, t)))
        counts = {}
        for name in ATTRIBUTES:
            qd = self.quant[name]
            actual = attribute(frame, name, self.sh_dim)
            if name in PREDICTED:
                p = pred[name][slot]
                if name == "quats":  # q and -q: compare on the prediction's side
                    actual = np.where((actual * p).sum(1, keepdims=True) < 0, -actual, actual)
                step = np.float32(qd["tol"])
                now = p + d.res[name][slot].astype(np.float32) * step
                if name != "means":
                    now = _unit(now)
                err = np.abs(actual - now).max(1)
                codes = np.clip(np.rint((actual - p) / step), -_I16, _I16).astype(np.int16)
                state = d.res[name]
            else:
                now = self._values(name, d.codes[name][slot])
                err = np.abs(actual - now).max(1)
                codes = codes_of(actual, qd)
                state = d.codes[name]
            send = np.flatnonzero(err > qd["tol"])
            order = send[np.argsort(slot[send], kind="stable")]
            counts[name] = int(len(order))
            if len(order):
                self.arrays[f"{prefix}.upd.{name}.idx"] = _delta(slot[order])
                self.arrays[f"{prefix}.upd.{name}.val"] = codes[order]
                state[slot[order]] = codes[order].astype(np.int64)
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
                 group: int = 0) -> tuple[dict, dict[str, np.ndarray]]:
    """(metadata, named arrays) of one group: `frames[0]` is its key frame; the others must
    carry the key frame's track ids for the Gaussians they share with it."""
    if not frames:
        raise ValueError("frames: a group needs at least its key frame")
    if sh_dim not in (0, 3, 8, 15):
        raise ValueError(f"sh_dim: expected 0, 3, 8 or 15 (SH degree 0-3), got {sh_dim}")
    for f in frames:
        if len(np.unique(f.ids)) != len(f):
            raise ValueError("frames: a frame repeats a track id; ids must be unique per frame")
    enc = _Encoder(frames, config, sh_dim, group)
    for i in range(len(frames)):
        enc.frame(i)
    return enc.meta, enc.arrays
