"""A skinned, animated glTF 2.0 character (a binary .glb) as a `dgs synth` subject: its mesh
posed at any time of its animation by linear blend skinning, textured by its base-colour map.

What is read (glTF 2.0 specification, Khronos): the first mesh of the scene that has a skin
(every primitive with POSITION, NORMAL, TEXCOORD_0, JOINTS_0, WEIGHTS_0 and indices), that
skin's joints and inverse bind matrices, the node hierarchy (matrix or translation / rotation /
scale), the first animation's channels (LINEAR, STEP or CUBICSPLINE samplers; rotations slerped)
and the base-colour texture of each primitive's material (an embedded PNG or JPEG, sRGB) times
its base-colour factor. Anything else the character needs and this reader lacks (sparse
accessors, external buffers, morph targets) is refused with a ValueError naming it.

Coordinates: glTF is +Y up in metres; the subject is turned to `dgs synth`'s +Z up, centred on
the z axis with its feet on z = 0 at time 0 (the figure's convention), real size kept.
"""

from __future__ import annotations

import io
import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from core.color import srgb_to_linear
from core.rotations import quat_to_rotmat
from core.synth.figure import FigureMesh

__all__ = ["ALBEDO_SCALE", "GltfCharacter", "sample_texture"]

_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
               5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
ALBEDO_SCALE = 0.35
"""Base colours are scaled by this to albedo, as a studio sets its exposure for the subject:
the capture light's irradiance reaches 2.6 on the key side (`core.synth.shading.LIGHTS`), so
a map's white (most of CesiumMan's suit) renders just under 1 instead of clipping, which would
erase its texture and what relighting could recover. The figure's palette (0.25-0.85 times a
0.6-1 checker) is about as dark on average."""
# glTF +Y up -> dgs synth +Z up: (x, y, z) -> (x, -z, y), a rotation (det +1).
_Y_UP_TO_Z_UP = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])


def _slerp(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    if np.dot(a, b) < 0:
        b = -b
    d = float(np.clip(np.dot(a, b), -1.0, 1.0))
    if d > 0.9995:
        q = a + s * (b - a)
    else:
        theta = np.arccos(d)
        q = (np.sin((1 - s) * theta) * a + np.sin(s * theta) * b) / np.sin(theta)
    return q / np.linalg.norm(q)


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, C) of `texture` (H, W, C) at glTF texture coordinates `uv` (N, 2)
    (origin at the image's top-left corner, u right, v down; repeated outside 0..1)."""
    h, w = texture.shape[:2]
    x = np.mod(uv[:, 0], 1.0) * w - 0.5
    y = np.mod(uv[:, 1], 1.0) * h - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, x1 = np.mod(x0, w), np.mod(x0 + 1, w)
    y0, y1 = np.mod(y0, h), np.mod(y0 + 1, h)
    top = texture[y0, x0] * (1 - fx) + texture[y0, x1] * fx
    bottom = texture[y1, x0] * (1 - fx) + texture[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


@dataclass(frozen=True)
class _Channel:
    node: int
    path: str
    times: np.ndarray
    values: np.ndarray
    """(K, C) keyframe values; CUBICSPLINE: (K, 3, C) in-tangent, value, out-tangent."""
    interpolation: str

    def at(self, t: float) -> np.ndarray:
        times, k = self.times, len(self.times)
        cubic = self.interpolation == "CUBICSPLINE"
        value = (lambda i: self.values[i, 1]) if cubic else (lambda i: self.values[i])
        if t <= times[0] or k == 1:
            return value(0)
        if t >= times[-1]:
            return value(k - 1)
        i = int(np.searchsorted(times, t, side="right")) - 1
        dt = float(times[i + 1] - times[i])
        s = (t - times[i]) / dt
        if self.interpolation == "STEP":
            return value(i)
        if cubic:  # Hermite spline with the keyframes' tangents scaled by the interval
            p0, m0 = self.values[i, 1], self.values[i, 2] * dt
            p1, m1 = self.values[i + 1, 1], self.values[i + 1, 0] * dt
            s2, s3 = s * s, s * s * s
            out = ((2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * m0
                   + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * m1)
            return out / np.linalg.norm(out) if self.path == "rotation" else out
        if self.path == "rotation":
            return _slerp(self.values[i], self.values[i + 1], s)
        return (1 - s) * self.values[i] + s * self.values[i + 1]


class GltfCharacter:
    """A skinned glTF character: `pose(t)` the mesh at `t` seconds of its animation (looped),
    `duration` its length, `texture` (H, W, 3) linear albedo."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        doc, binary = _read_glb(self.path)
        self._doc, self._bin = doc, binary
        self._parents = {c: i for i, n in enumerate(doc.get("nodes", []))
                         for c in n.get("children", [])}
        mesh_node = next((i for i, n in enumerate(doc.get("nodes", []))
                          if "mesh" in n and "skin" in n), None)
        if mesh_node is None:
            raise ValueError(f"{self.path}: no skinned mesh (a node with both 'mesh' and 'skin')")
        mesh = doc["meshes"][doc["nodes"][mesh_node]["mesh"]]
        skin = doc["skins"][doc["nodes"][mesh_node]["skin"]]
        parts = [self._primitive(p, k) for k, p in enumerate(mesh["primitives"])]
        offsets = np.cumsum([0] + [len(p["positions"]) for p in parts])
        self.rest = np.concatenate([p["positions"] for p in parts]).astype(np.float64)
        self._normals = np.concatenate([p["normals"] for p in parts]).astype(np.float64)
        self.uv = np.concatenate([p["uv"] for p in parts]).astype(np.float64)
        self._joints = np.concatenate([p["joints"] for p in parts]).astype(np.int64)
        self._weights = np.concatenate([p["weights"] for p in parts]).astype(np.float64)
        self._weights /= np.maximum(self._weights.sum(axis=1, keepdims=True), 1e-12)
        self.faces = np.concatenate([p["faces"] + o for p, o in zip(parts, offsets)])
        self.part = np.concatenate([np.full(len(p["positions"]), k) for k, p in enumerate(parts)])
        self.textures = [p["texture"] for p in parts]
        self.joint_nodes = list(skin["joints"])
        if "inverseBindMatrices" in skin:
            ibm = self._accessor(skin["inverseBindMatrices"]).reshape(-1, 4, 4)
            self._inverse_bind = np.transpose(ibm, (0, 2, 1)).astype(np.float64)  # column-major
        else:
            self._inverse_bind = np.tile(np.eye(4), (len(self.joint_nodes), 1, 1))
        if self._joints.max(initial=0) >= len(self.joint_nodes):
            raise ValueError(f"{self.path}: JOINTS_0 names joint {self._joints.max()} of a skin "
                             f"with {len(self.joint_nodes)}")
        anims = doc.get("animations", [])
        self._channels = [] if not anims else [self._channel(anims[0], c)
                                               for c in anims[0]["channels"]]
        self.duration = max((float(c.times[-1]) for c in self._channels), default=0.0)
        # Turned to +Z up; centred on the z axis with the feet on z = 0 at time 0.
        first = self._skinned(0.0)[0] @ _Y_UP_TO_Z_UP.T
        lo, hi = first.min(axis=0), first.max(axis=0)
        self._offset = -np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])

    @property
    def height(self) -> float:
        """Height of the character at time 0 (metres)."""
        return float(np.ptp(self.pose(0.0).vertices[:, 2]))

    # -- reading ---------------------------------------------------------------------------------
    def _accessor(self, index: int) -> np.ndarray:
        a = self._doc["accessors"][index]
        if "sparse" in a:
            raise ValueError(f"{self.path}: accessor {index} is sparse, which is not supported")
        if a["componentType"] not in _COMPONENTS or a["type"] not in _WIDTH:
            raise ValueError(f"{self.path}: accessor {index} has an unknown component type or "
                             f"type ({a['componentType']}, {a['type']})")
        dtype, width = np.dtype(_COMPONENTS[a["componentType"]]), _WIDTH[a["type"]]
        count = int(a["count"])
        if "bufferView" not in a:
            return np.zeros((count, width), dtype)
        view = self._doc["bufferViews"][a["bufferView"]]
        if view.get("buffer", 0) != 0:
            raise ValueError(f"{self.path}: buffer {view['buffer']} is external; only the .glb's "
                             "own binary chunk is read")
        start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
        stride = view.get("byteStride") or dtype.itemsize * width
        end = start + stride * (count - 1) + dtype.itemsize * width
        if end > len(self._bin) or end > view.get("byteOffset", 0) + view["byteLength"]:
            raise ValueError(f"{self.path}: accessor {index} reads past its buffer view")
        raw = np.lib.stride_tricks.as_strided(
            np.frombuffer(self._bin, dtype=np.uint8, count=end - start, offset=start),
            shape=(count, dtype.itemsize * width), strides=(stride, 1)).copy()
        out = raw.view(dtype).reshape(count, width)
        if a.get("normalized") and dtype.kind in "ui":
            out = out.astype(np.float64) / np.iinfo(dtype).max
        return out

    def _primitive(self, p: dict, k: int) -> dict:
        attrs = p.get("attributes", {})
        missing = [n for n in ("POSITION", "NORMAL", "TEXCOORD_0", "JOINTS_0", "WEIGHTS_0")
                   if n not in attrs]
        if missing or "indices" not in p:
            lacks = ", ".join(missing or ["indices"])
            raise ValueError(f"{self.path}: primitive {k} lacks {lacks}")
        if p.get("mode", 4) != 4:
            raise ValueError(f"{self.path}: primitive {k} is not a triangle list (mode "
                             f"{p['mode']})")
        if p.get("targets"):
            raise ValueError(f"{self.path}: primitive {k} has morph targets, not supported")
        faces = self._accessor(p["indices"]).reshape(-1, 3).astype(np.int64)
        n = int(self._doc["accessors"][attrs["POSITION"]]["count"])
        if faces.size and (faces.min() < 0 or faces.max() >= n):
            raise ValueError(f"{self.path}: primitive {k} indexes past its {n} vertices")
        return {"positions": self._accessor(attrs["POSITION"]),
                "normals": self._accessor(attrs["NORMAL"]),
                "uv": self._accessor(attrs["TEXCOORD_0"]).astype(np.float64),
                "joints": self._accessor(attrs["JOINTS_0"]),
                "weights": self._accessor(attrs["WEIGHTS_0"]).astype(np.float64),
                "faces": faces, "texture": self._base_colour(p.get("material"))}

    def _base_colour(self, material: int | None) -> np.ndarray:
        """(H, W, 3) linear albedo of a material (a 1 x 1 map of its factor without a texture)."""
        pbr = {} if material is None else self._doc["materials"][material].get(
            "pbrMetallicRoughness", {})
        factor = np.asarray(pbr.get("baseColorFactor", [1, 1, 1, 1]), np.float64)[:3]
        if "baseColorTexture" not in pbr:
            return factor[None, None, :] * ALBEDO_SCALE
        texture = self._doc["textures"][pbr["baseColorTexture"]["index"]]
        image = self._doc["images"][texture["source"]]
        if "bufferView" not in image:
            raise ValueError(f"{self.path}: image {texture['source']} is external; only images "
                             "embedded in the .glb are read")
        view = self._doc["bufferViews"][image["bufferView"]]
        start = view.get("byteOffset", 0)
        data = self._bin[start:start + view["byteLength"]]
        try:
            rgb = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), np.float64) / 255.0
        except OSError as exc:
            raise ValueError(f"{self.path}: image {texture['source']} cannot be decoded: "
                             f"{exc}") from None
        return srgb_to_linear(rgb) * factor * ALBEDO_SCALE

    def _channel(self, anim: dict, c: dict) -> _Channel:
        sampler = anim["samplers"][c["sampler"]]
        times = self._accessor(sampler["input"]).astype(np.float64).reshape(-1)
        values = self._accessor(sampler["output"]).astype(np.float64)
        mode = sampler.get("interpolation", "LINEAR")
        if mode not in ("LINEAR", "STEP", "CUBICSPLINE"):
            raise ValueError(f"{self.path}: unknown interpolation {mode!r}")
        if mode == "CUBICSPLINE":
            values = values.reshape(len(times), 3, -1)
        path = c["target"]["path"]
        if path not in ("translation", "rotation", "scale", "weights"):
            raise ValueError(f"{self.path}: unknown animation path {path!r}")
        return _Channel(int(c["target"].get("node", -1)), path, times, values, mode)

    # -- posing ----------------------------------------------------------------------------------
    def _local(self, index: int, t: float) -> np.ndarray:
        node = self._doc["nodes"][index]
        if "matrix" in node:
            return np.asarray(node["matrix"], np.float64).reshape(4, 4).T
        trs = {"translation": np.asarray(node.get("translation", [0, 0, 0]), np.float64),
               "rotation": np.asarray(node.get("rotation", [0, 0, 0, 1]), np.float64),
               "scale": np.asarray(node.get("scale", [1, 1, 1]), np.float64)}
        for ch in self._channels:
            if ch.node == index and ch.path in trs:
                trs[ch.path] = ch.at(t)
        m = np.eye(4)
        x, y, z, w = trs["rotation"]  # glTF stores x, y, z, w
        m[:3, :3] = quat_to_rotmat(np.array([w, x, y, z])) * trs["scale"][None, :]
        m[:3, 3] = trs["translation"]
        return m

    def _world(self, index: int, t: float, cache: dict) -> np.ndarray:
        if index not in cache:
            local = self._local(index, t)
            parent = self._parents.get(index)
            cache[index] = local if parent is None else self._world(parent, t, cache) @ local
        return cache[index]

    def _skinned(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Skinned positions and unit normals (glTF axes) at time t (looped over `duration`)."""
        if self.duration > 0:
            t = float(np.mod(t, self.duration))
        cache: dict = {}
        joints = np.stack([self._world(j, t, cache) for j in self.joint_nodes]) @ self._inverse_bind
        blend = np.einsum("vk,vkab->vab", self._weights, joints[self._joints])  # (V, 4, 4)
        positions = np.einsum("vab,vb->va", blend[:, :3, :3], self.rest) + blend[:, :3, 3]
        # Normals by the inverse transpose of each vertex's blended linear part.
        normals = np.einsum("vba,vb->va", np.linalg.inv(blend[:, :3, :3]), self._normals)
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        return positions, normals

    def pose(self, t: float) -> FigureMesh:
        """The mesh at `t` seconds (+Z up, world coordinates of `dgs synth`)."""
        positions, normals = self._skinned(t)
        return FigureMesh(vertices=positions @ _Y_UP_TO_Z_UP.T + self._offset, faces=self.faces,
                          normals=normals @ _Y_UP_TO_Z_UP.T, rest=self.rest, part=self.part)

    def albedo(self, part: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(N, 3) linear albedo of points on primitives `part` (N,) at texture coordinates
        `uv` (N, 2)."""
        out = np.zeros((len(part), 3))
        for k, texture in enumerate(self.textures):
            sel = part == k
            if sel.any():
                out[sel] = sample_texture(texture, uv[sel])
        return out


def _read_glb(path: Path) -> tuple[dict, bytes]:
    """(JSON document, binary chunk) of a .glb file, ValueError naming what is wrong."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc}") from None
    if len(data) < 20 or data[:4] != b"glTF":
        raise ValueError(f"{path}: not a binary glTF file (.glb: starts with 'glTF')")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2:
        raise ValueError(f"{path}: glTF version {version}; only 2 is read")
    if length > len(data):
        raise ValueError(f"{path}: truncated ({len(data)} bytes of {length})")
    doc, binary, offset = None, b"", 12
    while offset + 8 <= length:
        size, kind = struct.unpack_from("<II", data, offset)
        chunk = data[offset + 8:offset + 8 + size]
        if len(chunk) != size:
            raise ValueError(f"{path}: truncated chunk at byte {offset}")
        if kind == 0x4E4F534A:  # "JSON"
            try:
                doc = json.loads(chunk)
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise ValueError(f"{path}: the JSON chunk does not parse: {exc}") from None
        elif kind == 0x004E4942:  # "BIN\0"
            binary = chunk
        offset += 8 + size
    if doc is None:
        raise ValueError(f"{path}: no JSON chunk")
    return doc, binary
