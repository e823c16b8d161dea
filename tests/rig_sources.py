"""Issue 39's importer cases, written from a real capture by the tests themselves (the importer
tests in tests/core and the API tests): a rig in a mirrored world (every rotation of determinant
-1, with its points), a rig half mirrored, poses stored the other way round (camera-to-world in
Panoptic's `w2c`, world-to-camera in transforms.json's `transform_matrix`), and an IDR folder
with `images/` and `masks/` for `image/` and `mask/`."""

from __future__ import annotations

import dataclasses
import io
import json
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["MIRROR_Z", "Y_DOWN", "files_of", "idr_files", "inverted", "mirrored",
           "panoptic_files", "points_npz", "transforms_files", "turned", "write"]

MIRROR_Z = np.diag([1.0, 1.0, -1.0, 1.0])
"""The world mirrored along z: a source in it has every rotation of determinant -1."""
Y_DOWN = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
"""From the synthetic capture's z-up world to a y-down one (up is -y), as Panoptic's."""


def turned(capture, world_from_old: np.ndarray, ids: set[str] | None = None):
    """`capture` with its world changed by the 4x4 `world_from_old` (for the cameras `ids`,
    default all): each world_to_camera becomes world_to_camera @ inv(world_from_old)."""
    back = np.linalg.inv(world_from_old)
    cams = tuple(dataclasses.replace(c, world_to_camera=c.world_to_camera @ back)
                 if ids is None or c.id in ids else c for c in capture.cameras)
    return dataclasses.replace(capture, cameras=cams)


def mirrored(capture, ids: set[str] | None = None):
    """`capture` in a world mirrored along z (only the cameras `ids`, when given)."""
    return turned(capture, MIRROR_Z, ids)


def files_of(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes()
            for p in sorted(root.rglob("*")) if p.is_file()}


def write(files: dict[str, bytes], root: Path) -> Path:
    for rel, data in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    return root


def points_npz(points: np.ndarray) -> bytes:
    """Panoptic's init_pt_cld.npz of `points` (N, 3): x, y, z, r, g, b, seg per row."""
    data = np.concatenate([points, np.full((len(points), 3), 0.5), np.ones((len(points), 1))],
                          axis=1)
    buf = io.BytesIO()
    np.savez(buf, data=data)
    return buf.getvalue()


def panoptic_files(capture) -> dict[str, bytes]:
    """`capture` in the Panoptic layout (its first camera held out)."""
    from core.data.importers.panoptic import export_panoptic

    with tempfile.TemporaryDirectory() as tmp:
        export_panoptic(capture, Path(tmp), test_cameras=[capture.cameras[0].id])
        return files_of(Path(tmp))


def transforms_files(capture) -> dict[str, bytes]:
    from core.data.importers.transforms import export_transforms

    with tempfile.TemporaryDirectory() as tmp:
        export_transforms(capture, Path(tmp))
        return files_of(Path(tmp))


def idr_files(capture, plural: bool = False) -> dict[str, bytes]:
    """`capture`'s first frame as IDR writes it (`image/`, `mask/`), or with `images/` and
    `masks/` when `plural`."""
    from core.data.importers.idr import export_idr

    with tempfile.TemporaryDirectory() as tmp:
        export_idr(capture, Path(tmp))
        files = files_of(Path(tmp))
    if plural:
        files = {("images/" + k[6:] if k.startswith("image/") else
                  "masks/" + k[5:] if k.startswith("mask/") else k): v
                 for k, v in files.items()}
    return files


def inverted(files: dict[str, bytes]) -> dict[str, bytes]:
    """The source `files` with every pose matrix replaced by its inverse: Panoptic's `w2c` then
    holds camera-to-world, transforms.json's `transform_matrix` world-to-camera."""
    out = dict(files)
    for name in ("train_meta.json", "test_meta.json", "transforms.json"):
        if name not in out:
            continue
        doc = json.loads(out[name])
        if "w2c" in doc:
            doc["w2c"] = [[np.linalg.inv(m).tolist() for m in frame] for frame in doc["w2c"]]
        for entry in doc.get("frames", []) if isinstance(doc.get("frames"), list) else []:
            entry["transform_matrix"] = np.linalg.inv(entry["transform_matrix"]).tolist()
        out[name] = json.dumps(doc).encode()
    return out
