"""IDR / NeuS captures (``cameras.npz`` or ``cameras_sphere.npz`` + ``image/`` + ``mask/``, or
``images/`` + ``masks/`` as some preparations name them): reader and writer.

As public multi-view surface datasets ship them (DTU and BlendedMVS in IDR's layout, NeuS's
cases): ``world_mat_i`` is the 3x4 (or 4x4) projection ``K [R | t]`` of the i-th image in sorted
order, ``scale_mat_i`` (4x4, identity when absent) maps the normalised object sphere to that
world. The capture's world is the normalised one (``P = world_mat @ scale_mat``, the object
inside the unit sphere as the datasets intend); the import record's ``source_from_world`` is
``scale_mat`` (from the normalised world back to the source's). Each projection is decomposed
into K and a rigid pose (RQ decomposition); of the two poses a projection allows (it is
defined up to a scale of either sign), the one with the normalised world's centre, the object,
in front of the camera is taken, so a mirrored world keeps its determinant -1 for the rig
checks (`core.data.importers.rig`) instead of putting the object behind every camera. Pixel
centres sit at integer coordinates in these datasets (rays through ``K^-1 [u, v, 1]`` for
integer u, v), so 0.5 is added to cx and cy.
A decomposed K has rounding-level skew: below ``SKEW_TOLERANCE`` of fx it is dropped and the
import record notes it; a larger skew is refused (our cameras have none).
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import TypeAdapter

from core.data.capture import Camera, Capture, CaptureError, Problem
from core.data.images import ImageReadError, image_size
from core.data.importers.common import (
    ImportedCapture,
    PoseSource,
    SourceView,
    safe_name,
    source_transform,
)
from core.data.importers.records import MAX_CAMERAS, checked, load_npz, matrix
from core.data.rules import name_problem
from core.data.schema import extrinsics_problems, intrinsics_problems

__all__ = ["SKEW_TOLERANCE", "decompose_projection", "drop_skew", "export_idr",
           "find_cameras_npz", "read_idr"]

SKEW_TOLERANCE = 1e-3
"""Largest |skew| / fx dropped on import (a decomposed K's rounding is ~1e-7 of fx)."""
_NPZ_NAMES = ("cameras.npz", "cameras_sphere.npz")
_FOLDERS = (("image", "mask"), ("images", "masks"))
"""IDR's and NeuS's folder names, and the plural ones of other preparations."""
_IMAGE_EXTS = (".png", ".jpg", ".jpeg")


def find_cameras_npz(src: Path) -> Path | None:
    """The camera file of an IDR/NeuS folder (or the file itself), or None."""
    src = Path(src)
    if src.is_file():
        return src if src.suffix == ".npz" else None
    for name in _NPZ_NAMES:
        if (src / name).is_file():
            return src / name
    return None


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """K (3, 3) with K[2, 2] = 1 and positive focal lengths, and the world-to-camera (4, 4) of
    a 3x4 projection P = s K [R | t] (any scale s != 0): of the two (R, t) and (-R, -t) that
    s allows, the one with the world's origin in front of the camera (R of determinant -1
    when that world is mirrored), the proper one when the origin is on the camera's plane."""
    P = np.asarray(P, dtype=np.float64)[:3, :4]
    M, p4 = P[:, :3], P[:, 3]
    if np.linalg.det(M) < 0:  # start from det(R) = +1, then let the origin decide
        M, p4 = -M, -p4
    # RQ decomposition from QR of the row-reversed transpose: M = K R, K upper triangular.
    flip = np.eye(3)[::-1]
    q, r = np.linalg.qr((flip @ M).T)
    K, R = flip @ r.T @ flip, flip @ q.T
    signs = np.diag(np.sign(np.diag(K)))  # positive diagonal; signs @ signs = I
    K, R = K @ signs, signs @ R
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, np.linalg.solve(K, p4)
    if w2c[2, 3] < 0:  # the origin behind: the other sign of s is the camera
        w2c[:3, :4] *= -1.0
    return K / K[2, 2], w2c


def drop_skew(K: np.ndarray, tolerance: float = SKEW_TOLERANCE) -> tuple[np.ndarray, str | None]:
    """K without its skew K[0, 1] and a note saying what was dropped (None when there was none);
    ValueError saying how large when |skew| exceeds `tolerance` x fx."""
    skew, fx = float(K[0, 1]), float(K[0, 0])
    ratio = abs(skew) / abs(fx) if fx else float("inf")
    if ratio <= 1e-9:  # the decomposition's own rounding: nothing to note
        out = K.copy()
        out[0, 1] = 0.0
        return out, None
    if ratio > tolerance:
        raise ValueError(f"K has a skew of {skew:.6g} px ({ratio:.3g} of fx = {fx:.6g}); only a "
                         f"skew below {tolerance:g} of fx is dropped on import. Resample the "
                         "images to a camera without skew first")
    out = K.copy()
    out[0, 1] = 0.0
    return out, f"skew {skew:.3g} px ({ratio:.2g} of fx) dropped"


_WORLD_MAT = TypeAdapter(matrix(4, 4, least_rows=3))
_SCALE_MAT = TypeAdapter(matrix(4, 4))


def _sorted_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_EXTS)


def _projection(i: int, name: str, mats: dict[str, np.ndarray], where: Path,
                problems: list[Problem]) -> tuple[np.ndarray, np.ndarray] | None:
    """(P = world_mat @ scale_mat, scale_mat) of camera i, its arrays parsed as matrices."""
    if f"world_mat_{i}" not in mats:
        problems.append(Problem(str(where), f"world_mat_{i}: is missing (image {name})"))
        return None
    n = len(problems)
    world = checked(_WORLD_MAT, mats[f"world_mat_{i}"].tolist(), where, f"world_mat_{i}",
                    problems)
    scale = checked(_SCALE_MAT, mats[f"scale_mat_{i}"].tolist(), where, f"scale_mat_{i}",
                    problems) if f"scale_mat_{i}" in mats else np.eye(4).tolist()
    if len(problems) > n:
        return None
    with np.errstate(all="ignore"):  # huge entries overflow: refused just below
        P = np.asarray(world, np.float64)[:3, :4] @ np.asarray(scale, np.float64)
        det = float(np.linalg.det(P[:, :3])) if np.isfinite(P).all() else 0.0
    if not abs(det) >= 1e-12:
        problems.append(Problem(str(where), f"world_mat_{i} @ scale_mat_{i} is singular or "
                                            "not finite"))
        return None
    return P, np.asarray(scale, np.float64)


def _camera(i: int, image: Path, mats: dict[str, np.ndarray], size: tuple[int, int],
            where: Path, problems: list[Problem]) -> tuple[Camera, np.ndarray, str | None] | None:
    name = image.name
    problem = name_problem(Path(name).stem)
    if problem is not None:
        problems.append(Problem(str(image), f"image name {problem}"))
        return None
    made = _projection(i, name, mats, where, problems)
    if made is None:
        return None
    P, scale = made
    try:
        with np.errstate(all="ignore"):
            K, w2c = decompose_projection(P)
        K, note = drop_skew(K)
    except (ValueError, np.linalg.LinAlgError) as exc:
        problems.append(Problem(str(where), f"camera {i} ({name}): {exc}"))
        return None
    K[0, 2] += 0.5  # integer pixel centres in the source, +0.5 in ours (docs/design.md 3.1)
    K[1, 2] += 0.5
    K[1, 0] = K[2, 0] = K[2, 1] = 0.0
    bad = intrinsics_problems(K) + extrinsics_problems(w2c, proper=False)  # rig checks: det -1
    problems.extend(Problem(str(where), f"camera {i} ({name}): {m}") for m in bad)
    return Camera(safe_name(Path(name).stem), size[0], size[1], K, w2c), scale, note


def read_idr(src: str | Path) -> ImportedCapture:
    """Read an IDR/NeuS folder; raises :class:`CaptureError` listing every problem."""
    src = Path(src)
    npz = find_cameras_npz(src)
    if npz is None:
        raise CaptureError([Problem(str(src), f"no {' or '.join(_NPZ_NAMES)} found")])
    root = npz.parent
    image_dir, mask_dir = _folders(root)
    images, masks = _sorted_files(image_dir), _sorted_files(mask_dir)
    problems: list[Problem] = []
    if not images:
        problems.append(Problem(str(image_dir), "no images (image/*.png or .jpg, or images/) "
                                                "found"))
    if len(images) > MAX_CAMERAS:
        raise CaptureError([Problem(str(image_dir), f"holds {len(images)} images; a "
                                    f"capture may have {MAX_CAMERAS} cameras")])
    if masks and len(masks) != len(images):
        problems.append(Problem(str(mask_dir), f"{len(masks)} masks for {len(images)} "
                                               "images; expected one per image"))
    mats = load_npz(npz)
    cameras, views, notes, scales = [], [], {}, []
    for i, image in enumerate(images):
        try:
            size = image_size(image)
        except ImageReadError as exc:
            problems.append(Problem(str(exc.path), exc.message))
            continue
        made = _camera(i, image, mats, size, npz, problems)
        if made is None:
            continue
        cam, scale, note = made
        cameras.append(cam)
        scales.append(scale)
        if note:
            notes[cam.id] = note
        views.append(SourceView("000000", cam.id, image, masks[i] if masks else None))
    if len({c.id for c in cameras}) != len(cameras):
        problems.append(Problem(str(image_dir), "image names collide once made ids"))
    if scales and any(not np.allclose(s, scales[0]) for s in scales):
        problems.append(Problem(str(npz), "scale_mat differs between cameras; expected one "
                                          "normalisation for the whole capture"))
    if problems:
        raise CaptureError(problems)
    to_source = source_transform(np.eye(4), "world_mat @ scale_mat = [K | 0] @ world_to_camera, "
                                            "with cx, cy minus 0.5")
    to_source["source_from_world"] = scales[0].tolist()
    record: dict[str, Any] = {"format": "idr", "source": str(src.resolve()), "file": npz.name,
                              "to_source": to_source, "pixel_centres": "integer in the source",
                              "notes": notes}
    up = _estimate_up(cameras)
    return ImportedCapture(cameras, ["000000"], up, views, record, [npz],
                           poses=PoseSource(npz, "world_mat_i @ scale_mat_i", "projection"))


def _folders(root: Path) -> tuple[Path, Path]:
    """(image folder, mask folder): IDR's ``image/`` + ``mask/``, else ``images/`` +
    ``masks/``; CaptureError when both image folders hold images (which is the capture?)."""
    held = [(image, mask) for image, mask in _FOLDERS if _sorted_files(root / image)]
    if len(held) > 1:
        raise CaptureError([Problem(str(root), "both image/ and images/ hold images; keep the "
                                    "one the cameras belong to")])
    image, mask = held[0] if held else _FOLDERS[0]
    return root / image, root / mask


def _estimate_up(cameras: list[Camera]) -> tuple[float, float, float]:
    # No fixed up in these datasets; cameras are held upright, so their mean -y axis is it.
    up = np.mean([-c.R[1] for c in cameras], axis=0)
    up = up / max(float(np.linalg.norm(up)), 1e-12)
    return (float(up[0]), float(up[1]), float(up[2]))


def export_idr(capture: Capture, dst: str | Path, *, scale_mat: np.ndarray | None = None,
               name: str = "cameras.npz") -> Path:
    """Write the first frame of `capture` as `dst`/`name` + image/ (+ mask/ when every view has
    one), camera i the i-th image: world_mat_i its projection in the capture's world, and
    `scale_mat` (default identity) from a normalised world to the capture's, as the datasets'
    (importing the result gives a capture in that normalised world)."""
    dst = Path(dst)
    S = np.eye(4) if scale_mat is None else np.asarray(scale_mat, dtype=np.float64)
    frame = capture.frames[0]
    masks = [capture.mask_path(frame, c.id) for c in capture.cameras]
    arrays: dict[str, np.ndarray] = {}
    for i, cam in enumerate(capture.cameras):
        src = capture.image_path(frame, cam.id)
        if src is None:
            raise FileNotFoundError(f"{capture.root}/images/{frame}/{cam.id}.*: missing image")
        (dst / "image").mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, dst / "image" / f"{i:06d}{src.suffix}")
        if all(m is not None for m in masks):
            (dst / "mask").mkdir(parents=True, exist_ok=True)
            shutil.copyfile(masks[i], dst / "mask" / f"{i:03d}.png")
        K = cam.K.copy()
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        world = np.eye(4)
        world[:3, :4] = K @ cam.world_to_camera[:3, :4]
        arrays[f"world_mat_{i}"] = world
        arrays[f"scale_mat_{i}"] = S
    np.savez(dst / name, **arrays)
    return dst / name
