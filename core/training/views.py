"""A frame's training views in memory, and which cameras train (every 8th is held out)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from core.data.capture import Camera
from core.data.dataset import CaptureDataset

__all__ = ["View", "frame_views", "training_cameras"]


@dataclass
class View:
    """One training view in memory: camera and (H, W, C) tensors."""

    camera: Camera
    image: Tensor
    mask: Tensor | None = None
    normal: Tensor | None = None

    @classmethod
    def from_sample(cls, sample) -> View:
        """From a `core.data.Sample`."""
        return cls(sample.camera, sample.image, sample.mask, sample.normal)

    def to(self, device: torch.device | str) -> View:
        """This view with its tensors on `device` (itself when they are there already): a
        fitter moves each view once, not every step."""
        moved = [None if t is None else t.to(device) for t in (self.image, self.mask,
                                                                 self.normal)]
        if all(a is b for a, b in zip(moved, (self.image, self.mask, self.normal))):
            return self
        return View(self.camera, *moved)


def training_cameras(cameras: Sequence[Camera]) -> list[Camera]:
    """Every camera except the held-out ones (index % 8 == 0, docs/design.md section 3.2)."""
    return [c for i, c in enumerate(cameras) if i % 8 != 0]


def frame_views(capture, frame: str, downscale: float = 1.0) -> list[View]:
    """The training views of one frame of a `core.data.Capture`, reduced by `downscale`."""
    if frame not in capture.frames:
        raise ValueError(f"frame: {frame!r} is not in the capture (frames "
                         f"{list(capture.frames)[:5]}...)")
    ids = [c.id for c in training_cameras(capture.cameras)]
    if not ids:
        raise ValueError("capture: no training camera (every 8th camera is held out, so at "
                         "least 2 are needed)")
    ds = CaptureDataset(capture, frames=[frame], cameras=ids, downscale=downscale)
    return [View.from_sample(ds[i]) for i in range(len(ds))]
