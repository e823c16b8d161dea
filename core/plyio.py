"""PLY files, read and written in one place on `plyfile`: the Gaussian layout of a frame
(docs/design.md section 3.3), the capture's seed points (`core.data.points`) and the
ground-truth triangle meshes of synthetic captures (`core.synth`). Torch-free (the API
validates a capture's points.ply with it).

Every reader takes ASCII and binary files of either byte order, any numeric property type and
elements it does not need (ignored), and raises ``ValueError`` naming the file and the problem.
Every writer writes binary little-endian, atomically (a temporary file renamed into place).

Gaussians are stored raw exactly as 3DGS stores them (logit opacities, log-scales,
unnormalized quaternions), float32, so a round trip is bit-identical; the standard vertex
properties come first so common splat viewers open the file, then the disentangled extras
``opacity_geo``, ``normal_x/y/z``, ``visibility`` and, in a sequence, an int ``track_id``.
``f_rest_*`` is channel-major as in 3DGS ``construct_list_of_attributes``: the 15 red
coefficients first.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyElementParseError, PlyParseError

from core.files import atomic_path

__all__ = ["gaussian_ply_properties", "read_gaussian_ply", "read_mesh_ply", "read_point_ply",
           "read_track_ids", "read_vertices", "write_gaussian_ply", "write_mesh_ply",
           "write_point_ply"]

_N_REST = 45
_REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
_EXTRAS = ["opacity_geo", "normal_x", "normal_y", "normal_z", "visibility"]


def _read(path: Path, lists: dict[str, dict[str, int]] | None = None) -> PlyData:
    """The whole file. Binary elements are memory-mapped (copy on write), which is what loads
    them as one array; `lists` gives fixed list lengths per element and property (a mesh's
    triangles), without which an element with a list property loads row by row."""
    try:
        with open(path, "rb") as fh:
            return PlyData.read(fh, mmap="c", known_list_len=lists or {})
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc.strerror}") from None
    except PlyElementParseError as exc:
        element = exc.element.name if exc.element is not None else "?"
        count = exc.element.count if exc.element is not None else "?"
        if exc.message == "early end-of-file":
            raise ValueError(f"{path}: truncated: element {element!r} has {exc.row} of its "
                             f"{count} rows") from None
        if exc.message == "unexpected list length" and lists:
            raise ValueError(f"{path}: element {element!r} row {exc.row}: only triangles are "
                             "supported") from None
        raise ValueError(f"{path}: {exc}") from None
    except PlyParseError as exc:
        if getattr(exc, "message", "") in ("expected 'ply'", "early end-of-file"):
            raise ValueError(f"{path}: not a PLY file (no 'ply' / 'end_header' lines)") from None
        raise ValueError(f"{path}: cannot read the PLY header: {exc}") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read: {exc}") from None


def read_vertices(path: str | os.PathLike[str]) -> np.ndarray:
    """The `vertex` element of a PLY file as a structured array (one field per property);
    list properties of vertices are refused."""
    path = Path(path)
    ply = _read(path)
    if "vertex" not in [e.name for e in ply.elements]:
        raise ValueError(f"{path}: no 'vertex' element")
    data = ply["vertex"].data
    if any(data.dtype[name].hasobject for name in data.dtype.names or ()):
        raise ValueError(f"{path}: list properties on vertices are not supported")
    return data


def _write(path: Path, elements: list[PlyElement]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        PlyData(elements, text=False, byte_order="<").write(fh)


def _array(value) -> np.ndarray:
    """A tensor (on any device, with or without grad) or an array as a float32 array."""
    if hasattr(value, "detach"):
        value = value.detach().cpu().float().numpy()
    return np.asarray(value, dtype=np.float32)


# -- Gaussians ------------------------------------------------------------------------------
def gaussian_ply_properties() -> list[str]:
    """Vertex property names in file order."""
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(_N_REST)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
            + _EXTRAS)


def _columns(params: dict) -> np.ndarray:
    n = _array(params["means"]).shape[0]

    def cols(name: str) -> np.ndarray:
        return _array(params[name]).reshape(n, -1)

    parts = [
        cols("means"),
        np.zeros((n, 3), np.float32),  # nx ny nz: unused by 3DGS, kept for viewers
        _array(params["sh0"]).transpose(0, 2, 1).reshape(n, 3),
        _array(params["shN"]).transpose(0, 2, 1).reshape(n, _N_REST),
        cols("opacity_c"), cols("scales"), cols("quats"), cols("opacity_g"), cols("normals"),
        cols("visibility"),
    ]
    return np.concatenate(parts, axis=1)


def write_gaussian_ply(path: str | os.PathLike[str], params: dict,
                       track_ids: np.ndarray | None = None) -> None:
    """Write raw Gaussian parameters (names of `core.model.PARAM_NAMES`; tensors or arrays) as
    binary PLY, atomically. `track_ids` (N,) adds an int property `track_id`: the same
    Gaussian has the same id in every frame of a group (core.sequence)."""
    data = np.ascontiguousarray(_columns(params), dtype="<f4")
    names = gaussian_ply_properties()
    assert data.shape[1] == len(names)
    fields = [(name, "<f4") for name in names]
    if track_ids is None:
        rec = data.view(np.dtype(fields)).reshape(-1)
    else:
        ids = np.asarray(track_ids, dtype=np.int64).reshape(-1)
        if ids.shape[0] != data.shape[0] or (ids.size and not 0 <= ids.min() <= ids.max() < 2**31):
            raise ValueError(f"track_ids: expected {data.shape[0]} ids in 0..2^31-1")
        rec = np.empty(data.shape[0], dtype=fields + [("track_id", "<i4")])
        for i, name in enumerate(names):
            rec[name] = data[:, i]
        rec["track_id"] = ids
    _write(Path(path), [PlyElement.describe(rec, "vertex")])


def read_gaussian_ply(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Raw parameters (float32 arrays, shapes of `core.model.GaussianModel`) from a Gaussian
    PLY. Plain 3DGS files (no extras, or fewer SH degrees) load with zero higher SH,
    opacity_geo = opacity, normals +z, visibility 0.9."""
    path = Path(path)
    try:
        v = read_vertices(path)
    except ValueError as exc:
        raise ValueError(f"path: {exc}") from None
    count, names = len(v), set(v.dtype.names or ())
    missing = [name for name in _REQUIRED if name not in names]
    if missing:
        raise ValueError(f"path: {path} lacks vertex properties {missing}")

    def cols(*keys: str) -> np.ndarray:
        return np.stack([v[k].astype(np.float32) for k in keys], axis=1).reshape(count, -1)

    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    if n_rest % 3 or n_rest > _N_REST:
        raise ValueError(f"path: {path} has {n_rest} f_rest properties; expected 0, 9, 24 or 45")
    rest = np.zeros((count, 3, _N_REST // 3), np.float32)
    if n_rest:
        per = n_rest // 3
        rest[:, :, :per] = cols(*[f"f_rest_{i}" for i in range(n_rest)]).reshape(count, 3, per)
    out = {
        "means": cols("x", "y", "z"),
        "sh0": cols("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :],
        "shN": np.ascontiguousarray(rest.transpose(0, 2, 1)),
        "opacity_c": cols("opacity")[:, 0],
        "scales": cols("scale_0", "scale_1", "scale_2"),
        "quats": cols("rot_0", "rot_1", "rot_2", "rot_3"),
    }
    if set(_EXTRAS) <= names:
        out["opacity_g"] = cols("opacity_geo")[:, 0]
        out["normals"] = cols("normal_x", "normal_y", "normal_z")
        out["visibility"] = cols("visibility")
    else:
        out["opacity_g"] = out["opacity_c"].copy()
        out["normals"] = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (count, 1))
        out["visibility"] = np.full((count, 1), math.log(0.9 / 0.1), np.float32)
    return out


def read_track_ids(path: str | os.PathLike[str]) -> np.ndarray | None:
    """(N,) int64 `track_id` of a Gaussian PLY, or None when the file has none."""
    try:
        v = read_vertices(path)
    except ValueError as exc:
        raise ValueError(f"path: {exc}") from None
    return v["track_id"].astype(np.int64) if "track_id" in (v.dtype.names or ()) else None


# -- points ---------------------------------------------------------------------------------
def read_point_ply(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray | None]:
    """(points (N, 3) float64, colours (N, 3) float32 in 0..1 or None) of a PLY's vertices:
    x, y, z and, when present, red, green, blue (8-bit integers, or floats in 0..1)."""
    path = Path(path)
    v = read_vertices(path)
    fields = list(v.dtype.names or ())
    if not {"x", "y", "z"} <= set(fields):
        raise ValueError(f"{path}: vertices need x, y and z properties, got {fields}")
    points = np.stack([v[k].astype(np.float64) for k in "xyz"], axis=1).reshape(len(v), 3)
    if not np.isfinite(points).all():
        raise ValueError(f"{path}: vertex coordinates contain NaN or Inf")
    if not {"red", "green", "blue"} <= set(fields):
        return points, None
    # Integer colours are 8-bit (0..255), float ones already 0..1.
    scale = 1.0 if v.dtype["red"].kind == "f" else 255.0
    rgb = np.stack([v[k].astype(np.float64) for k in ("red", "green", "blue")], axis=1)
    return points, np.clip(rgb.reshape(len(v), 3) / scale, 0, 1).astype(np.float32)


def write_point_ply(path: str | os.PathLike[str], points: np.ndarray,
                    colors: np.ndarray | None = None) -> None:
    """float x y z, uchar red green blue (grey without colours)."""
    rec = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, k in enumerate("xyz"):
        rec[k] = points[:, i]
    colors = colors if colors is not None else np.full((len(points), 3), 0.5)
    rgb = np.clip(np.round(colors * 255), 0, 255).astype(np.uint8)
    for i, k in enumerate(("red", "green", "blue")):
        rec[k] = rgb[:, i]
    _write(Path(path), [PlyElement.describe(rec, "vertex")])


# -- triangle meshes ------------------------------------------------------------------------
def write_mesh_ply(path: str | os.PathLike[str], vertices: np.ndarray, faces: np.ndarray,
                   normals: np.ndarray | None = None) -> None:
    """float32 vertices (V, 3) [+ normals nx ny nz] and int32 triangle faces (T, 3)."""
    props = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals is not None else [])
    cols = [vertices] + ([normals] if normals is not None else [])
    vdata = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f4")
    vrec = vdata.view(np.dtype([(p, "<f4") for p in props])).reshape(-1)
    frec = np.empty(len(faces), dtype=[("vertex_indices", "<i4", (3,))])
    frec["vertex_indices"] = faces
    _write(Path(path), [PlyElement.describe(vrec, "vertex"),
                        PlyElement.describe(frec, "face", len_types={"vertex_indices": "u1"})])


def read_mesh_ply(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, triangle faces (T, 3) int64) of a triangle mesh PLY."""
    path = Path(path)
    ply = _read(path, lists={"face": {"vertex_indices": 3}})
    names = [e.name for e in ply.elements]
    if "vertex" not in names or "face" not in names:
        raise ValueError(f"{path}: a mesh needs 'vertex' and 'face' elements, got {names}")
    v = ply["vertex"].data
    verts = np.stack([v[k].astype(np.float64) for k in "xyz"], axis=1).reshape(len(v), 3)
    faces = np.asarray(ply["face"].data["vertex_indices"], dtype=np.int64).reshape(-1, 3)
    return verts, faces
