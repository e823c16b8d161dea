"""What no one format can check of an imported rig, done once for every reader's cameras
(:func:`settle_rig`, which ``read_source`` runs): the handedness of its world and the direction
of its poses (docs/capture-format.md, "Mirrored worlds and inverted poses").

**Handedness.** A rotation of determinant -1 is a mirrored world (a tool that made a y-up world
z-up, or flipped an axis, by a sign). When every camera has one, the world is mirrored back
once for the whole rig: each world-to-camera is multiplied on the right by the reflection ``F``
of one world axis, the one least along ``up``, so every camera keeps its own axes (its image is
unchanged) and its rotation becomes proper; the points, ``up`` and the record's way back
(``to_source.source_from_world``) carry ``F`` too, and the record's ``warnings`` say so. A rig
whose cameras disagree is refused naming them: no one reflection fixes both kinds.

**Direction.** Poses the wrong way round are refused by `core.data.importers.direction`.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np

from core.data.capture import CaptureError, Problem
from core.data.importers.common import ImportedCapture
from core.data.importers.direction import check_direction
from core.data.points import PointCloud

__all__ = ["settle_rig"]

_NAMED = 8


def settle_rig(imported: ImportedCapture) -> ImportedCapture:
    """`imported` with a mirrored world mirrored back (noted in its record's ``warnings``);
    :class:`CaptureError` for a rig of mixed handedness or poses the wrong way round."""
    dets = [float(np.linalg.det(c.R)) for c in imported.cameras]
    if any(d < 0 for d in dets) and not all(d < 0 for d in dets):
        raise CaptureError([_mixed(imported, dets)])
    check_direction(imported)  # on the poses as the source gives them
    if dets and all(d < 0 for d in dets):
        imported = _mirrored(imported)
    return imported


def _where(imported: ImportedCapture) -> tuple[str, str]:
    """(file, field) of the poses, for messages."""
    poses = imported.poses
    if poses is None:
        return str(imported.record.get("source", "source")), "poses"
    return str(poses.file), poses.field


def _listed(ids: list[str]) -> str:
    """``cameras a, b and 3 more`` (``camera a`` alone)."""
    more = f" and {len(ids) - _NAMED} more" if len(ids) > _NAMED else ""
    return ("camera " if len(ids) == 1 else "cameras ") + ", ".join(ids[:_NAMED]) + more


def _mixed(imported: ImportedCapture, dets: list[float]) -> Problem:
    neg = [c.id for c, d in zip(imported.cameras, dets) if d < 0]
    pos = [c.id for c, d in zip(imported.cameras, dets) if d > 0]
    file, field = _where(imported)
    return Problem(file, f"{field}: the rotations of {_listed(neg)} have determinant -1 "
                         f"(a mirrored world) and those of {_listed(pos)} +1; one rig "
                         "has one world, so no single reflection makes them all proper: "
                         "recalibrate, or fix the poses of the cameras in the wrong world")


def _mirrored(imported: ImportedCapture) -> ImportedCapture:
    if any(v.normal is not None for v in imported.views):  # no reader gives any today
        file, field = _where(imported)
        raise CaptureError([Problem(file, f"{field}: every rotation has determinant -1 (a "
                                    "mirrored world) and the views have normal priors, which "
                                    "are not mirrored on import: leave the normals out")])
    up = np.asarray(imported.up, np.float64)
    axis = int(np.argmin(np.abs(up)))  # a reflection that keeps `up` (near) where it was
    F = np.eye(4)
    F[axis, axis] = -1.0
    cameras = [dataclasses.replace(c, world_to_camera=c.world_to_camera @ F)
               for c in imported.cameras]
    points = imported.points
    if points is not None:
        points = PointCloud(points.points @ F[:3, :3], points.colors)
    new_up = F[:3, :3] @ up + 0.0  # + 0.0: no -0.0 in capture.json
    record = copy.deepcopy(imported.record)
    to_source = record.setdefault("to_source", {})
    back = np.asarray(to_source.get("source_from_world", np.eye(4)), np.float64)
    to_source["source_from_world"] = (back @ F).tolist()
    name = "xyz"[axis]
    record["mirrored_axis"] = name
    file, field = _where(imported)
    record.setdefault("warnings", []).append(
        f"{field}: every camera's rotation has determinant -1 (a mirrored world); the world was "
        f"mirrored back along its {name} axis ({name} -> -{name}) for every camera"
        f"{' and the points' if points is not None else ''}, so the images are unchanged and "
        "the rotations proper (import.to_source.source_from_world leads back to the source)")
    return dataclasses.replace(imported, cameras=cameras, points=points, record=record,
                               up=(float(new_up[0]), float(new_up[1]), float(new_up[2])))
