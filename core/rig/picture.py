"""The seeds picture of a key frame (RUN/plots/seeds-<frame>.png): a training view, its seeds
drawn over it in their own colours, and the same seeds coloured by where they came from, so a
glance tells whether the fused points cover the scene."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from PIL import Image, ImageDraw

from core.data.capture import Camera
from core.data.points import PointCloud
from core.files import atomic_path

__all__ = ["SOURCE_COLOURS", "seeds_picture"]

SOURCE_COLOURS: dict[str, tuple[int, int, int]] = {
    "fused": (60, 220, 90), "capture": (60, 220, 90), "subject": (250, 120, 30),
    "triangulated": (250, 220, 40), "random": (200, 80, 220), "background": (70, 140, 250),
    "static": (70, 200, 200),
}


def _splat(canvas: np.ndarray, camera: Camera, points: np.ndarray, colours: np.ndarray,
           depth_order: bool = True) -> None:
    """Draw points (N, 3) one pixel each with colours (N, 3) in 0..255, nearest last."""
    uv, z = camera.project(points)
    u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    h, w = canvas.shape[:2]
    ok = (z > 0) & (u >= 0) & (v >= 0) & (u < w) & (v < h)
    order = np.argsort(-z[ok]) if depth_order else np.arange(int(ok.sum()))
    canvas[v[ok][order], u[ok][order]] = colours[ok][order]


def seeds_picture(path: str | os.PathLike[str], camera: Camera, image: np.ndarray,
                  parts: Sequence[tuple[str, PointCloud]], title: str = "") -> None:
    """Write three panels side by side: `image` (H, W, 3) in 0..1 seen by `camera`, the seeds
    in their colours over it darkened, the seeds coloured by source (`SOURCE_COLOURS`), with a
    legend of the counts."""
    base = (np.clip(image[..., :3], 0, 1) * 255).astype(np.uint8)
    own = (base * 0.3).astype(np.uint8)
    by_source = (base * 0.3).astype(np.uint8)
    for name, cloud in parts:
        if not len(cloud):
            continue
        cols = cloud.colors if cloud.colors is not None else np.full((len(cloud), 3), 0.5)
        _splat(own, camera, cloud.points, (np.clip(cols, 0, 1) * 255).astype(np.uint8))
        _splat(by_source, camera, cloud.points,
               np.tile(np.array(SOURCE_COLOURS.get(name, (255, 255, 255)), np.uint8),
                       (len(cloud), 1)))
    lines = [title] if title else []
    lines += [f"{name}: {len(cloud)}" for name, cloud in parts]
    panels = np.concatenate([base, own, by_source], axis=1)
    legend = np.zeros((12 * len(lines) + 4, panels.shape[1], 3), np.uint8)  # below: small views
    sheet = Image.fromarray(np.concatenate([panels, legend], axis=0))
    draw = ImageDraw.Draw(sheet)
    for i, line in enumerate(lines):
        colour = SOURCE_COLOURS.get(line.split(":")[0], (255, 255, 255))
        draw.text((4, base.shape[0] + 2 + 12 * i), line, fill=colour)
    with atomic_path(path) as tmp:
        sheet.save(tmp, format="PNG")
