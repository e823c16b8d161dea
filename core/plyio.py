"""Gaussian PLY files (docs/design.md section 3.3): the standard 3DGS vertex layout, so common splat
viewers open them, plus the disentangled extras ``opacity_geo``, ``normal_x/y/z``, ``visibility``.

Values are stored raw exactly as 3DGS stores them (logit opacities, log-scales, unnormalized
quaternions), float32 little endian, so a round trip is bit-identical. ``f_rest_*`` is
channel-major as in 3DGS ``construct_list_of_attributes``: the 15 red coefficients first.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from core.files import atomic_path

__all__ = ["gaussian_ply_properties", "read_gaussian_ply", "read_track_ids", "write_gaussian_ply"]

_N_REST = 45
_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1",
          "uint8": "u1", "char": "i1", "int8": "i1", "short": "<i2", "ushort": "<u2",
          "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4"}


def gaussian_ply_properties() -> list[str]:
    """Vertex property names in file order."""
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(_N_REST)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
               "opacity_geo", "normal_x", "normal_y", "normal_z", "visibility"])


def _columns(params: dict[str, Tensor]) -> np.ndarray:
    n = params["means"].shape[0]

    def cpu(name: str) -> np.ndarray:
        return params[name].detach().to("cpu", torch.float32).numpy().reshape(n, -1)

    parts = [
        cpu("means"),
        np.zeros((n, 3), np.float32),  # nx ny nz: unused by 3DGS, kept for viewers
        params["sh0"].detach().cpu().float().transpose(1, 2).reshape(n, 3).numpy(),
        params["shN"].detach().cpu().float().transpose(1, 2).reshape(n, _N_REST).numpy(),
        cpu("opacity_c"), cpu("scales"), cpu("quats"), cpu("opacity_g"), cpu("normals"),
        cpu("visibility"),
    ]
    return np.concatenate(parts, axis=1)


def write_gaussian_ply(path: str | os.PathLike[str], params: dict[str, Tensor],
                       track_ids: np.ndarray | Tensor | None = None) -> None:
    """Write raw Gaussian parameters (names of `core.model.PARAM_NAMES`) as binary PLY,
    atomically (a temporary file renamed into place). `track_ids` (N,) adds an int property
    `track_id`: the same Gaussian has the same id in every frame of a group (core.sequence)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = np.ascontiguousarray(_columns(params), dtype="<f4")
    names = gaussian_ply_properties()
    assert data.shape[1] == len(names)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {data.shape[0]}"]
    header += [f"property float {name}" for name in names]
    if track_ids is not None:
        ids = np.asarray(track_ids, dtype=np.int64).reshape(-1)
        if ids.shape[0] != data.shape[0] or (ids.size and not 0 <= ids.min() <= ids.max() < 2**31):
            raise ValueError(f"track_ids: expected {data.shape[0]} ids in 0..2^31-1")
        rec = np.empty(data.shape[0], dtype=[(n, "<f4") for n in names] + [("track_id", "<i4")])
        for i, name in enumerate(names):
            rec[name] = data[:, i]
        rec["track_id"] = ids
        data = rec
        header.append("property int track_id")
    header.append("end_header")
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(data.tobytes())


def _parse_header(path: Path, raw: bytes) -> tuple[int, np.dtype, int]:
    marker = b"end_header\n"
    end = raw.find(marker)
    if not raw.startswith(b"ply\n") or end < 0:
        raise ValueError(f"path: {path} is not a PLY file (no 'ply' / 'end_header' lines)")
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise ValueError(f"path: {path} must be binary little-endian PLY")
    count, fields, element = 0, [], None
    for line in lines:
        parts = line.split()
        if parts[:1] == ["element"]:
            element = parts[1]
            if element == "vertex":
                count = int(parts[2])
            elif int(parts[2]) > 0:
                raise ValueError(f"path: {path} has element {element!r}; expected only vertices")
        elif parts[:1] == ["property"] and element == "vertex":
            if parts[1] not in _TYPES:
                raise ValueError(f"path: {path} property {parts[-1]!r} has unsupported type "
                                 f"{parts[1]!r}")
            fields.append((parts[2], _TYPES[parts[1]]))
    return count, np.dtype(fields), end + len(marker)


def read_gaussian_ply(path: str | os.PathLike[str]) -> dict[str, Tensor]:
    """Read raw parameters from a Gaussian PLY. Plain 3DGS files (no extras, or fewer SH
    degrees) load with zero higher SH, opacity_geo = opacity, normals +z, visibility 0.9."""
    path = Path(path)
    raw = path.read_bytes()
    count, dtype, offset = _parse_header(path, raw)
    if len(raw) - offset < count * dtype.itemsize:
        raise ValueError(f"path: {path} is truncated: {count} vertices need "
                         f"{count * dtype.itemsize} bytes, found {len(raw) - offset}")
    v = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
    names = set(dtype.names or ())
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
                "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [name for name in required if name not in names]
    if missing:
        raise ValueError(f"path: {path} lacks vertex properties {missing}")

    def cols(*keys: str) -> Tensor:
        return torch.from_numpy(np.stack([v[k].astype(np.float32) for k in keys], axis=1))

    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    if n_rest % 3 or n_rest > _N_REST:
        raise ValueError(f"path: {path} has {n_rest} f_rest properties; expected 0, 9, 24 or 45")
    rest = torch.zeros(count, 3, _N_REST // 3)
    if n_rest:
        per = n_rest // 3
        rest[:, :, :per] = cols(*[f"f_rest_{i}" for i in range(n_rest)]).reshape(count, 3, per)
    out = {
        "means": cols("x", "y", "z"),
        "sh0": cols("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :],
        "shN": rest.transpose(1, 2).contiguous(),
        "opacity_c": cols("opacity")[:, 0],
        "scales": cols("scale_0", "scale_1", "scale_2"),
        "quats": cols("rot_0", "rot_1", "rot_2", "rot_3"),
    }
    extras = {"opacity_geo", "normal_x", "normal_y", "normal_z", "visibility"}
    if extras <= names:
        out["opacity_g"] = cols("opacity_geo")[:, 0]
        out["normals"] = cols("normal_x", "normal_y", "normal_z")
        out["visibility"] = cols("visibility")
    else:
        out["opacity_g"] = out["opacity_c"].clone()
        out["normals"] = torch.tensor([[0.0, 0.0, 1.0]]).repeat(count, 1)
        out["visibility"] = torch.full((count, 1), math.log(0.9 / 0.1))
    return out


def read_track_ids(path: str | os.PathLike[str]) -> np.ndarray | None:
    """(N,) int64 `track_id` of a Gaussian PLY, or None when the file has none."""
    path = Path(path)
    raw = path.read_bytes()
    count, dtype, offset = _parse_header(path, raw)
    if "track_id" not in (dtype.names or ()):
        return None
    v = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
    return v["track_id"].astype(np.int64)
