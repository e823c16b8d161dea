"""An articulated, skinned figure: capsule body parts on a 10-bone skeleton, posed per frame.

World is z-up, metres, the figure stands on z = 0 facing -y. Limbs are single tubes skinned to two
bones with a smooth blend across the elbow/knee, so posing bends the surface (non-rigid motion),
not just moves rigid pieces. Everything is deterministic given the seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BONES", "Figure", "FigureMesh"]

BONES = (
    "root",
    "neck",
    "l_upper",
    "l_fore",
    "r_upper",
    "r_fore",
    "l_thigh",
    "l_shin",
    "r_thigh",
    "r_shin",
)
_B = {name: i for i, name in enumerate(BONES)}


@dataclass(frozen=True)
class FigureMesh:
    """One posed frame: triangle mesh plus what the renderer needs per vertex."""

    vertices: np.ndarray
    """(V, 3) float64 world positions."""
    faces: np.ndarray
    """(T, 3) int64, counter-clockwise seen from outside."""
    normals: np.ndarray
    """(V, 3) unit vertex normals (area-weighted)."""
    rest: np.ndarray
    """(V, 3) rest-pose positions; the solid texture is evaluated on these, so it moves along."""
    part: np.ndarray
    """(V,) int part index (for per-part colours)."""


def _capsule(r0: float, r1: float, length: float, n_around: int, n_cap: int, n_mid: int):
    """Capsule along +z from z=0 to z=length (caps beyond), radius tapering r0 -> r1.

    Returns local vertices (V, 3), faces (T, 3) and the axial coordinate s of each vertex.
    """
    rings: list[tuple[float, float]] = []  # (axial position, ring radius)
    for k in range(1, n_cap + 1):
        a = k / n_cap * np.pi / 2
        rings.append((-r0 * np.cos(a), r0 * np.sin(a)))
    for k in range(1, n_mid):
        s = k / n_mid * length
        rings.append((s, r0 + (r1 - r0) * s / max(length, 1e-9)))
    for k in range(n_cap, 0, -1):
        a = k / n_cap * np.pi / 2
        rings.append((length + r1 * np.cos(a), r1 * np.sin(a)))
    theta = np.arange(n_around) * 2 * np.pi / n_around
    verts = [[0.0, 0.0, -r0]]
    for s, rho in rings:
        verts += [[rho * np.cos(t), rho * np.sin(t), s] for t in theta]
    verts.append([0.0, 0.0, length + r1])
    verts = np.array(verts)
    n, faces = n_around, []
    ring0 = lambda i: 1 + i * n  # noqa: E731 - tiny local index helper
    for j in range(n):  # bottom fan
        faces.append([0, ring0(0) + (j + 1) % n, ring0(0) + j])
    for i in range(len(rings) - 1):
        for j in range(n):
            a, b = ring0(i) + j, ring0(i) + (j + 1) % n
            c, d = ring0(i + 1) + j, ring0(i + 1) + (j + 1) % n
            faces += [[a, b, d], [a, d, c]]
    top = len(verts) - 1
    for j in range(n):
        faces.append([top, ring0(len(rings) - 1) + j, ring0(len(rings) - 1) + (j + 1) % n])
    return verts, np.array(faces, dtype=np.int64), verts[:, 2].copy()


def _frame_along(direction: np.ndarray) -> np.ndarray:
    """Rotation whose third column is ``direction`` (maps local +z onto it)."""
    z = direction / np.linalg.norm(direction)
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


@dataclass(frozen=True)
class _Part:
    start: tuple[float, float, float]
    end: tuple[float, float, float]
    r0: float
    r1: float
    bones: tuple[str, str]
    split: float  # axial position where the second bone takes over (inf: single bone)
    squash: tuple[float, float] = (1.0, 1.0)
    n_around: int = 20


def _parts() -> list[_Part]:
    inf = float("inf")
    parts = [
        _Part((0, 0, 0.98), (0, 0, 1.40), 0.15, 0.18, ("root", "root"), inf, (1.0, 0.65), 32),
        _Part((0, 0, 1.44), (0, 0, 1.56), 0.05, 0.05, ("neck", "neck"), inf),
        _Part((0, 0, 1.68), (0, 0, 1.70), 0.11, 0.11, ("neck", "neck"), inf, (0.9, 1.0), 28),
    ]
    for side, sx in (("l", 1.0), ("r", -1.0)):
        shoulder = np.array([0.25 * sx, 0, 1.43])
        wrist = shoulder + 0.58 * np.array([0.15 * sx, 0, -1]) / np.hypot(0.15, 1)
        parts.append(
            _Part(
                tuple(shoulder), tuple(wrist), 0.055, 0.04, (f"{side}_upper", f"{side}_fore"), 0.30
            )
        )
        hip = np.array([0.10 * sx, 0, 0.98])
        ankle = np.array([0.11 * sx, 0, 0.12])
        parts.append(
            _Part(tuple(hip), tuple(ankle), 0.08, 0.05, (f"{side}_thigh", f"{side}_shin"), 0.43)
        )
        parts.append(
            _Part(
                (0.11 * sx, 0.02, 0.06),
                (0.11 * sx, -0.16, 0.05),
                0.045,
                0.04,
                (f"{side}_shin", f"{side}_shin"),
                inf,
            )
        )
    return parts


class Figure:
    """The rest-pose figure and its skinning; :meth:`pose` gives the mesh of one frame."""

    def __init__(self, seed: int = 0, detail: int = 1):
        rng = np.random.default_rng(seed)
        self.phase = rng.uniform(0, 2 * np.pi, size=4)
        verts, faces, bones, weights, parts = [], [], [], [], []
        offset = 0
        for pi, part in enumerate(_parts()):
            start, end = np.array(part.start), np.array(part.end)
            length = float(np.linalg.norm(end - start))
            n_mid = max(2, int(round(length / 0.03 * detail)))
            v, f, s = _capsule(part.r0, part.r1, length, part.n_around * detail, 5 * detail, n_mid)
            v[:, 0] *= part.squash[0]
            v[:, 1] *= part.squash[1]
            v = v @ _frame_along(end - start).T + start
            blend = np.clip((s - (part.split - 0.06)) / 0.12, 0.0, 1.0)
            blend = blend * blend * (3 - 2 * blend)  # smoothstep: no kink in the skinned surface
            verts.append(v)
            faces.append(f + offset)
            bones.append(np.tile([_B[part.bones[0]], _B[part.bones[1]]], (len(v), 1)))
            weights.append(np.stack([1 - blend, blend], axis=1))
            parts.append(np.full(len(v), pi))
            offset += len(v)
        self.rest = np.concatenate(verts)
        self.faces = np.concatenate(faces)
        self.bone_index = np.concatenate(bones)
        self.bone_weight = np.concatenate(weights)
        self.part = np.concatenate(parts)
        self.n_parts = len(_parts())

    def bone_transforms(self, t: float) -> np.ndarray:
        """(10, 4, 4) bone transforms at time ``t`` (in frames); limbs swing, elbows/knees bend."""
        p = self.phase
        w = 0.9  # radians per frame: consecutive frames differ visibly even for short sequences
        root = _about((0, 0, 0.98), _rot_z(0.25 * np.sin(w * t + p[0]))) @ _translate(
            (0, 0, 0.02 * np.sin(2 * w * t))
        )
        mats = {
            "root": root,
            "neck": root @ _about((0, 0, 1.44), _rot_x(0.2 * np.sin(w * t + p[1]))),
        }
        for side, sx, sign in (("l", 1.0, 1.0), ("r", -1.0, -1.0)):
            swing = sign * 0.6 * np.sin(w * t + p[2])
            shoulder = np.array([0.25 * sx, 0, 1.43])
            elbow = shoulder + 0.30 * np.array([0.15 * sx, 0, -1]) / np.hypot(0.15, 1)
            bend = 0.2 + 0.55 * (1 + np.sin(w * t + p[3] + (0 if side == "l" else np.pi)))
            upper = root @ _about(
                shoulder, _rot_x(swing) @ _rot_y(-sx * 0.15 * (1 + np.sin(w * t)))
            )
            mats[f"{side}_upper"] = upper
            mats[f"{side}_fore"] = upper @ _about(elbow, _rot_x(-bend))  # hand forward (-y)
            hip, knee = np.array([0.10 * sx, 0, 0.98]), np.array([0.105 * sx, 0, 0.55])
            leg = -swing * 0.7
            thigh = root @ _about(hip, _rot_x(leg))
            mats[f"{side}_thigh"] = thigh
            mats[f"{side}_shin"] = thigh @ _about(
                knee, _rot_x(0.1 + 0.45 * (1 + np.sin(w * t + p[3] + sign)))
            )  # foot back
        return np.stack([mats[b] for b in BONES])

    def pose(self, t: float) -> FigureMesh:
        mats = self.bone_transforms(t)
        homog = np.concatenate([self.rest, np.ones((len(self.rest), 1))], axis=1)
        out = np.zeros_like(self.rest)
        for k in range(2):  # linear blend skinning with two influences per vertex
            m = mats[self.bone_index[:, k]]
            out += self.bone_weight[:, k : k + 1] * np.einsum("vij,vj->vi", m[:, :3], homog)
        return FigureMesh(out, self.faces, vertex_normals(out, self.faces), self.rest, self.part)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit normals, area-weighted average of adjacent face normals."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _translate(t) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def _about(center, R: np.ndarray) -> np.ndarray:
    """Rotation ``R`` about the point ``center`` as a 4x4 matrix."""
    m = np.eye(4)
    m[:3, :3] = R
    c = np.asarray(center, dtype=np.float64)
    m[:3, 3] = c - R @ c
    return m
