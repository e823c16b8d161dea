"""A frame's training views in memory, as a run's `core.config.Views` select them."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from core.config.views import Views, select_views
from core.data.capture import Camera
from core.data.dataset import CaptureDataset

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
    normal_measured: Tensor | None = None
    """(H, W, 1) 1 where the confidence is a measurement's (stereo's plane fits), 0 where a
    guess's (the visual hull's); None: all measured (`LossWeights.normal_confidence`)."""

    @classmethod
    def from_sample(cls, sample, subject: bool = False) -> View:
        """From a `core.data.Sample`; its mask is the matte, or with `subject` (the run's
        masks mark a subject, `core.config.Views.subject`) only where the subject is."""
        if subject:
            return cls(sample.camera, sample.image, None, sample.normal, sample.mask)
        return cls(sample.camera, sample.image, sample.mask, sample.normal)

    @property
    def subject_mask(self) -> Tensor | None:
        """Where the subject is: the subject mask, else the matte, else None."""
        return self.subject if self.subject is not None else self.mask

    def to(self, device: torch.device | str) -> View:
        """This view with its tensors on `device` (itself when they are there already): a
        fitter moves each view once, not every step."""
        fields = (self.image, self.mask, self.normal, self.subject, self.normal_weight,
                  self.normal_measured)
        moved = [None if t is None else t.to(device) for t in fields]
        if all(a is b for a, b in zip(moved, fields)):
            return self
        return View(self.camera, *moved)


def training_cameras(capture, views: Views | None = None) -> list[Camera]:
    """The cameras of a `core.data.Capture` that train under `views` (None: the capture's
    defaults, `core.config.select_views`)."""
    return (views or select_views(capture)).cameras(capture, "training")


def frame_views(capture, frame: str, views: Views | None = None) -> list[View]:
    """The training views of one frame of a `core.data.Capture` as `views` selects them (its
    cameras, size and masks; None: the capture's defaults, `core.config.select_views`)."""
    if frame not in capture.frames:
        raise ValueError(f"frame: {frame!r} is not in the capture (frames "
                         f"{list(capture.frames)[:5]}...)")
    views = views or select_views(capture)
    ds = CaptureDataset(capture, frames=[frame], cameras=list(views.split.training),
                        downscale=views.downscale, matte=views.matte)
    return [View.from_sample(ds[i], views.subject) for i in range(len(ds))]
