"""What a running reconstruction tells its caller: `Progress` events (every step, checkpoint
and frame), a cooperative stop (`Stopped`), and the per-step history metrics.json and the
plots keep."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch

from core.metrics import psnr_of_mse
from core.training import Callback, CheckpointCallback, Fitter, StepInfo

LOSS_EVERY = 10
"""Steps between the loss a step event carries (reading it waits for the device)."""

__all__ = ["History", "Hooks", "Progress", "Stopped"]


@dataclass(frozen=True)
class Progress:
    """One event of a running reconstruction, for `reconstruct(on_progress=...)`."""

    kind: Literal["frame_start", "step", "checkpoint", "frame_done"]
    """What happened: a frame starts (or resumes), a step ended, a checkpoint is complete on disk
    (`path`), a frame's outputs are written."""
    frame: str
    """The frame's name."""
    frame_index: int
    """Its position among the selected frames (0-based)."""
    frames: int
    """How many frames the run has."""
    step: int
    """Steps of this frame done so far (after the step for kind 'step')."""
    iterations: int
    """Steps of this frame."""
    stage: int
    """Training stage of the last step (1, 2, 3; 0 before the first)."""
    gaussians: int = 0
    """Gaussians in the model."""
    loss: float | None = None
    """Total loss of the step (kind 'step')."""
    path: str | None = None
    """The checkpoint file (kind 'checkpoint') or the frame's folder (kind 'frame_done')."""
    phase: Literal["key", "deform", "refine"] = "key"
    """How the frame is made: static stages (a group's key frame), or the deform / refine stage
    of a frame deformed from its predecessor."""
    notes: tuple[str, ...] = ()
    """kind 'frame_start': what the fitter noted while it was made (where its initial points
    came from, a fallback to random points), for the job's log."""


class Stopped(Exception):
    """`reconstruct` stopped because `should_stop()` said so: after a step, with the frame's
    checkpoint written first, so `resume=True` continues from the step it stopped at; or,
    `step` None, before the frame began (its setup, seeds included, not spent), every frame
    before it finished."""

    def __init__(self, frame: str, step: int | None):
        super().__init__(f"stopped at step {step} of frame {frame} (checkpoint written)"
                         if step is not None else f"stopped before frame {frame} began")
        self.frame, self.step = frame, step

    @property
    def where(self) -> str:
        """Where it stopped, for a log: 'step 57', 'the start of frame 000003'."""
        return f"step {self.step}" if self.step is not None else f"the start of frame {self.frame}"


class History(Callback):
    """Per-step records for metrics.json and the plots (survives resume via the checkpoint).
    A step's numbers stay on the device until `records` is read or `every` steps have
    gathered: then all of them come back in one read (a GPU step never waits for the host)."""

    def __init__(self, every: int = 100) -> None:
        self._records: list[dict] = []
        self._pending: list[StepInfo] = []
        self.every = every

    @property
    def records(self) -> list[dict]:
        self._flush()
        return self._records

    @records.setter
    def records(self, value: list[dict]) -> None:
        self._pending, self._records = [], list(value)

    def on_step_end(self, trainer: Fitter, info: StepInfo) -> None:
        self._pending.append(info)
        if len(self._pending) >= self.every:
            self._flush()

    def _flush(self) -> None:
        if not self._pending:
            return
        values = [v for i in self._pending for v in
                  ([] if i.mse is None else [i.mse]) + list(i.terms.values())]
        flat = iter(torch.stack(values).tolist())
        for i in self._pending:
            mse = None if i.mse is None else next(flat)
            self._records.append({"step": i.step, "stage": i.plan.stage,
                                  "gaussians": i.n_gaussians,
                                  "psnr": None if mse is None else psnr_of_mse(mse),
                                  "seconds": i.seconds, **{k: next(flat) for k in i.terms}})
        self._pending = []


class Hooks(Callback):
    """Hands `Progress` events to the caller and stops (after a checkpoint) when asked to."""

    def __init__(self, frame: str, index: int, frames: int,
                 on_progress: Callable[[Progress], None] | None,
                 should_stop: Callable[[], bool] | None):
        self.frame, self.index, self.frames = frame, index, frames
        self.on_progress, self.should_stop = on_progress, should_stop
        self.saver: CheckpointCallback | None = None
        self.trainer: Fitter | None = None
        self.stage = 0
        self.loss: float | None = None

    def emit(self, kind: str, trainer: Fitter | None = None,
             path: str | None = None) -> None:
        trainer = trainer or self.trainer
        if self.on_progress is None or trainer is None:
            return
        self.on_progress(Progress(
            kind=kind, frame=self.frame, frame_index=self.index, frames=self.frames,
            step=trainer.step, iterations=trainer.iterations, stage=self.stage,
            gaussians=len(trainer.model), loss=self.loss if kind == "step" else None, path=path,
            phase=trainer.phase, notes=tuple(trainer.notes) if kind == "frame_start" else ()))

    def on_train_start(self, trainer: Fitter) -> None:
        self.trainer = trainer
        self.emit("frame_start", trainer)

    def on_step_end(self, trainer: Fitter, info: StepInfo) -> None:
        self.stage = info.plan.stage
        if self.loss is None or info.step % LOSS_EVERY == 0 \
                or trainer.step >= trainer.iterations:
            self.loss = info.losses["total"]  # a read-back: not every step
        self.emit("step", trainer)
        last = trainer.step >= trainer.iterations
        if self.should_stop is not None and not last and self.should_stop():
            if self.saver is not None:
                self.saver.save(trainer)
            raise Stopped(self.frame, trainer.step)
