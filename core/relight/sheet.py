"""The contact sheet of a run (RUN/contact_sheet.png, written by `dgs eval`): one row per
held-out view, columns capture | render | normal | AO | relit under each map of
core.relight.metrics.SHEET_MAPS, and for a synthetic capture also the view relit under its second
light beside that light's ground truth, and the ground-truth normals.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from core.files import atomic_path
from core.relight.output import to_uint8

__all__ = ["contact_sheet"]

LABEL_HEIGHT = 16


def _resize(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return np.asarray(Image.fromarray(image).convert("RGB").resize(size, Image.NEAREST))


def _png(path: Path, size: tuple[int, int]) -> np.ndarray:
    if not path.is_file():
        return np.zeros((size[1], size[0], 3), np.uint8)
    return _resize(np.asarray(Image.open(path).convert("RGB")), size)


def _captured(capture_dir: Path, frame: str, cam: str) -> Path:
    """The captured image of (frame, cam), whichever 8-bit format the capture holds (.png or
    .jpg; an .exr shows as black: the sheet does not tone-map)."""
    for ext in (".png", ".jpg", ".jpeg"):
        path = capture_dir / "images" / frame / f"{cam}{ext}"
        if path.is_file():
            return path
    return capture_dir / "images" / frame / f"{cam}.png"


TILE_MAX = 512
"""Longest side of a tile in pixels: a real capture's 1080x1920 views stay a readable sheet."""


def _capture_tile(capture_dir: Path, frame: str, cam: str, size: tuple[int, int],
                  matte: bool = True) -> np.ndarray:
    """The captured view as the camera saw it: straight colour, times its coverage mask when
    the masks are mattes (on the black of the synthetic studio); a subject mask leaves the
    scene around the subject in the picture, as the run reconstructs it."""
    image = _png(_captured(capture_dir, frame, cam), size).astype(np.float32)
    mask = capture_dir / "masks" / frame / f"{cam}.png"
    if matte and mask.is_file():
        cover = np.asarray(Image.open(mask).convert("L").resize(size, Image.NEAREST)) / 255.0
        image = image * cover[..., None]
    return (image + 0.5).astype(np.uint8)


def _gt_normal(capture_dir: Path, frame: str, cam: str, size) -> np.ndarray | None:
    path = capture_dir / "gt" / "normals" / frame / f"{cam}.npy"
    if not path.is_file():
        return None
    n = np.load(path)
    fg = np.linalg.norm(n, axis=-1, keepdims=True) > 0.5
    return _resize((np.where(fg, (n + 1) / 2, 0) * 255 + 0.5).astype(np.uint8), size)


def contact_sheet(capture_dir: Path, run_dir: Path, views: list[tuple[str, str]],
                  relit: dict[tuple[str, str], dict[str, np.ndarray]], out: Path,
                  scale: int = 2, matte: bool = True) -> Path:
    """Write the sheet of `views` ((frame, camera) pairs) to `out`; `relit[(frame, camera)]`
    maps a column name to an sRGB picture (H, W, 3) in 0..1 (the same names in every row).
    Tiles are the rendered view's size (else the captured image's) times `scale` (nearest
    neighbour), at most TILE_MAX pixels on the longer side; captured images may be .png or .jpg.
    `matte`: the run read the capture's masks as mattes (the capture tile is cut by them); off,
    they mark a subject inside a scene reconstructed whole and the tile stays whole."""
    if not views:
        raise ValueError("views: expected at least one (frame, camera) to show")
    rows, names = [], None
    for frame, cam in views:
        r = run_dir / "renders" / frame
        # Tiles at the render's size (the run's resolution) times `scale`, at most TILE_MAX.
        base = r / f"{cam}_rgb.png"
        first = Image.open(base if base.is_file() else _captured(capture_dir, frame, cam))
        factor = min(float(scale), TILE_MAX / max(first.width, first.height, 1))
        size = (max(1, round(first.width * factor)), max(1, round(first.height * factor)))
        pictures = relit.get((frame, cam), {})
        gt_normal = _gt_normal(capture_dir, frame, cam, size)
        tiles = {"capture": _capture_tile(capture_dir, frame, cam, size, matte),
                 "render": _png(r / f"{cam}_rgb.png", size),
                 "normal": _png(r / f"{cam}_normal.png", size),
                 "AO": _png(r / f"{cam}_ao.png", size),
                 **{name.removeprefix("builtin:"): _resize(to_uint8(img), size)
                    for name, img in pictures.items()}}
        if gt_normal is not None:
            tiles["ground-truth normal"] = gt_normal
        names = names or list(tiles)
        rows.append(np.concatenate([tiles.get(n, np.zeros_like(tiles["capture"]))
                                    for n in names], axis=1))
    width = max(row.shape[1] for row in rows)
    body = np.concatenate([np.pad(row, ((0, 0), (0, width - row.shape[1]), (0, 0)))
                           for row in rows], axis=0)
    sheet = Image.new("RGB", (body.shape[1], body.shape[0] + LABEL_HEIGHT), (255, 255, 255))
    sheet.paste(Image.fromarray(body), (0, LABEL_HEIGHT))
    draw = ImageDraw.Draw(sheet)
    tile = rows[0].shape[1] // len(names)
    for i, name in enumerate(names):
        draw.text((i * tile + 4, 2), name, fill=(0, 0, 0))
    with atomic_path(out) as tmp:
        sheet.save(tmp, format="PNG")
    return out
