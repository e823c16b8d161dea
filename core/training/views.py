"""A frame's training views in memory, and which cameras train (`core.data.split`)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from core.data.capture import Camera
from core.data.dataset import CaptureDataset
from core.data.split import camera_split

__all__ = ["View", "frame_views", "training_cameras"]


@dataclass
class View:
    """One training view in memory: camera and (H, W, C) tensors."""

    camera: Camera
    image: Tensor
    mask: Tensor | None = None
    """(H, W, 1) the matte: the picture counts only where it covers (None: all of it)."""
    normal: Tensor | None = None
    subject: Tensor | None = None
    """(H, W, 1) where the subject is, in a picture reconstructed whole (masks `subject`)."""
    normal_weight: Tensor | None = None
    """(H, W, 1) the normal prior's confidence in 0..1 (None: 1 wherever there is a prior)."""

    @classmethod
    def from_sample(cls, sample, masks: str = "matte") -> View:
        """From a `core.data.Sample`; its mask is the matte, or with `masks` subject only
        where the subject is."""
        if masks == "subject":
            return cls(sample.camera, sample.image, None, sample.normal, sample.mask)
        return cls(sample.camera, sample.image, sample.mask, sample.normal)

    @property
    def subject_mask(self) -> Tensor | None:
        """Where the subject is: the subject mask, else the matte, else None."""
        return self.subject if self.subject is not None else self.mask

    def to(self, device: torch.device | str) -> View:
        """This view with its tensors on `device` (itself when they are there already): a
        fitter moves each view once, not every step."""
        fields = (self.image, self.mask, self.normal, self.subject, self.normal_weight)
        moved = [None if t is None else t.to(device) for t in fields]
        if all(a is b for a, b in zip(moved, fields)):
            return self
        return View(self.camera, *moved)


def training_cameras(capture, split: str = "auto") -> list[Camera]:
    """The cameras of a `core.data.Capture` that train under `split` (`core.data.split`)."""
    ids = set(camera_split(capture, split).training)
    return [c for c in capture.cameras if c.id in ids]


def frame_views(capture, frame: str, downscale: float = 1.0, split: str = "auto",
                masks: str = "capture") -> list[View]:
    """The training views of one frame of a `core.data.Capture` under `split`, reduced by
    `downscale`, with its masks as `masks` says (`TrainConfig.masks`)."""
    if frame not in capture.frames:
        raise ValueError(f"frame: {frame!r} is not in the capture (frames "
                         f"{list(capture.frames)[:5]}...)")
    ids = list(camera_split(capture, split).training)
    use = capture.masks if masks == "capture" else masks
    ds = CaptureDataset(capture, frames=[frame], cameras=ids, downscale=downscale,
                        matte=use == "matte")
    return [View.from_sample(ds[i], use) for i in range(len(ds))]
