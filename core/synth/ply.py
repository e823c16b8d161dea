"""Binary little-endian PLY for triangle meshes (the ground-truth meshes of synthetic captures)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["read_ply", "write_ply"]


def write_ply(
    path: Path, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None
) -> None:
    """Write float32 vertices (V, 3) [+ normals] and int32 triangle faces (T, 3)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    props = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals is not None else [])
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}"]
    header += [f"property float {p}" for p in props]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    cols = [vertices] + ([normals] if normals is not None else [])
    vdata = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f4")
    fdata = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    fdata["n"] = 3
    fdata["i"] = faces
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vdata.tobytes())
        fh.write(fdata.tobytes())


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a mesh written by :func:`write_ply`: (vertices (V, 3) float64, faces (T, 3) int64)."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: only binary little-endian PLY is supported")
    n_v = n_f = 0
    n_props = 0
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            n_v = int(parts[2])
        elif parts[:2] == ["element", "face"]:
            n_f = int(parts[2])
        elif parts[:2] == ["property", "float"]:
            n_props += 1
    verts = np.frombuffer(data, dtype="<f4", count=n_v * n_props, offset=end).reshape(n_v, n_props)
    faces = np.frombuffer(
        data, dtype=[("n", "u1"), ("i", "<i4", (3,))], count=n_f, offset=end + verts.nbytes
    )
    if n_f and not np.all(faces["n"] == 3):
        raise ValueError(f"{path}: only triangle faces are supported")
    return verts[:, :3].astype(np.float64), faces["i"].astype(np.int64)
