"""The subject of a run: its frames' Gaussians inside the hull of the subject masks
(`core.sequence.hull`), what a studio delivers of a scene (the performers without the stage).

A group of pictures keeps its track ids from frame to frame, so the subject of a group is one
set of ids: those inside the hull in any of its frames (each frame judged at its own positions
against its own masks). Every frame of the group then keeps exactly those, so the stream's
groups stay in correspondence and a limb leaving the masks for a frame does not vanish.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from core.config import read_run
from core.data import load_capture
from core.export.splats import read_frame_ply
from core.render import RenderCamera
from core.sequence.hull import inside_hull
from core.training.views import frame_views

__all__ = ["subject_rows"]


def subject_rows(run: Path, groups: list[list[str]], capture_dir=None) -> dict[str, np.ndarray]:
    """{frame: (N,) bool rows of its PLY that are the subject's} for every frame of `groups`;
    ValueError when the run's capture has no masks to say where the subject is."""
    resolved = read_run(run, capture_dir)
    capture = load_capture(capture_dir if capture_dir is not None else resolved.capture)
    seq = resolved.config.sequence
    out: dict[str, np.ndarray] = {}
    for group in groups:
        ids = {f: read_frame_ply(run / "frames" / f / "gaussians.ply") for f in group}
        chosen: set[int] = set()
        for frame, splats in ids.items():
            views = frame_views(capture, frame, resolved.views)
            masked = [v.subject_mask for v in views]
            if all(m is None for m in masked):
                raise ValueError(f"subject: frame {frame} has no masks in the capture, so "
                                 "nothing says where the subject is")
            cams = [RenderCamera.from_camera(v.camera) for v in views]
            inside = inside_hull(torch.from_numpy(splats.means), cams, masked,
                                 dilate_pixels=seq.hull_dilate, share=seq.hull_share)
            chosen.update(splats.ids[inside.numpy()].tolist())
        keep = np.fromiter(chosen, dtype=np.int64, count=len(chosen))
        for frame, splats in ids.items():
            out[frame] = np.isin(splats.ids, keep)
    return out
