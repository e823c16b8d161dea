"""Fitting one frame: the shared step loop (`loop.FrameFitter`), the key-frame trainer with the
staged schedule (`keyframe.Trainer`), callbacks (progress, checkpoints) and the training views.
The tracked-frame fitter built on the same loop is `core.sequence.tracker.FrameTracker`."""

from core.training.callbacks import (
    Callback,
    CheckpointCallback,
    Fitter,
    ProgressCallback,
    StepInfo,
)
from core.training.keyframe import AOBaker, Trainer
from core.training.loop import FrameFitter
from core.training.views import View, frame_views, training_cameras

__all__ = [
    "AOBaker",
    "Callback",
    "CheckpointCallback",
    "Fitter",
    "FrameFitter",
    "ProgressCallback",
    "StepInfo",
    "Trainer",
    "View",
    "frame_views",
    "training_cameras",
]
