"""What runs around the step loop (in the manner of nerfstudio's engine/callbacks.py): the
record of a step, the callback hooks, a progress printer and the checkpoint writer. A callback
sees the loop as a `Fitter` (what `core.training.loop.FrameFitter` offers it), so this module
and the loop do not need each other's types."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Protocol, TextIO

import torch
from torch import Tensor

from core.metrics import psnr_of_mse
from core.model import GaussianModel
from core.stages import StagePlan

__all__ = ["Callback", "CheckpointCallback", "Fitter", "ProgressCallback", "StepInfo"]


class Fitter(Protocol):
    """The step loop as its callbacks see it (`core.training.loop.FrameFitter`)."""

    step: int
    """The next step to run (after a step's `on_step_end`: the steps done)."""
    model: GaussianModel
    phase: str
    """'key', or a tracked frame's 'deform' / 'refine'."""
    notes: list[str]
    """What the frame's log says about it (e.g. where its initial points came from)."""

    @property
    def iterations(self) -> int:
        """The frame's steps."""
        ...

    def save_checkpoint(self, path: str | os.PathLike[str], extra: object = None) -> None: ...


@dataclass
class StepInfo:
    """What a callback sees after each step. The step's numbers stay where they were computed
    (on a GPU, the device) until a callback reads `losses` or `psnr`: a step never waits for
    the device unless someone looks (a progress line every N steps, `History` in batches)."""

    step: int
    plan: StagePlan
    terms: dict[str, Tensor]
    """The loss terms and their "total", 0-dim tensors."""
    n_gaussians: int
    seconds: float
    """Host seconds of the step (on a GPU: its launches, not its device time)."""
    mse: Tensor | None = None
    """Mean squared error of this step's training render against its target, both on the
    configured background (comparable between steps whatever the step's random background)."""

    @cached_property
    def losses(self) -> dict[str, float]:
        """The terms as floats (one read-back for all)."""
        return dict(zip(self.terms, torch.stack(list(self.terms.values())).tolist()))

    @cached_property
    def psnr(self) -> float | None:
        """PSNR (dB) of `mse`."""
        return None if self.mse is None else psnr_of_mse(float(self.mse))


class Callback:
    """Hooks around a fitter's step loop; override what you need."""

    def on_train_start(self, trainer: Fitter) -> None: ...

    def on_step_end(self, trainer: Fitter, info: StepInfo) -> None: ...

    def on_train_end(self, trainer: Fitter) -> None: ...


class ProgressCallback(Callback):
    """Prints (or hands to `report`) a line every `every` steps."""

    def __init__(self, every: int = 100, stream: TextIO | None = None,
                 report: Callable[[StepInfo], None] | None = None):
        if every < 1:
            raise ValueError(f"every: expected >= 1, got {every}")
        self.every, self.stream, self.report = every, stream, report

    def on_step_end(self, trainer: Fitter, info: StepInfo) -> None:
        last = info.step == trainer.iterations - 1
        if info.step % self.every and not last:
            return
        if self.report is not None:
            self.report(info)
            return
        print(f"step {info.step + 1}/{trainer.iterations} stage {info.plan.stage} "
              f"loss {info.losses['total']:.4f} gaussians {info.n_gaussians} "
              f"{info.seconds:.1f}s", file=self.stream or sys.stdout)


class CheckpointCallback(Callback):
    """Writes `folder/<filename>` (atomically) every `every` steps and at the end; `extra`
    (a callable returning plain data) is stored beside the training state; `on_saved(path)` runs
    once the file is complete on disk (a service copies it off the machine there, so that a
    crashed worker's successor can resume from it)."""

    def __init__(self, folder: str | os.PathLike[str], every: int = 1000,
                 filename: str = "checkpoint.pt", extra: Callable[[], object] | None = None,
                 on_saved: Callable[[Path], None] | None = None):
        if every < 1:
            raise ValueError(f"every: expected >= 1, got {every}")
        self.folder, self.every, self.filename, self.extra = Path(folder), every, filename, extra
        self.on_saved = on_saved

    def save(self, trainer: Fitter) -> Path:
        """Write the checkpoint now; returns its path."""
        path = self.folder / self.filename
        trainer.save_checkpoint(path, extra=None if self.extra is None else self.extra())
        if self.on_saved is not None:
            self.on_saved(path)
        return path

    def on_step_end(self, trainer: Fitter, info: StepInfo) -> None:
        if (info.step + 1) % self.every == 0:
            self.save(trainer)

    def on_train_end(self, trainer: Fitter) -> None:
        self.save(trainer)
