"""How a command-line reconstruction shows its progress: a tqdm bar on a terminal, and on
anything else (a log file, `nohup`, a CI console) one line every so many seconds, so that a run
of hours is never silent. Both show the frame, stage, step, loss, Gaussians and an ETA (times in
tqdm's [h:]mm:ss).
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

from tqdm import tqdm

from core.training import Callback, StepInfo

__all__ = ["LogLines", "TerminalBar"]


class TerminalBar(Callback):
    """A tqdm bar for one frame: stage, iteration, loss, Gaussians, ETA."""

    def __init__(self, label: str):
        self.label, self.bar = label, None

    def on_train_start(self, trainer) -> None:
        self.bar = tqdm(total=trainer.iterations, initial=trainer.step,
                        desc=self.label, unit="it", dynamic_ncols=True, leave=True)

    def on_step_end(self, trainer, info: StepInfo) -> None:
        self.bar.update(1)
        if info.step % 10 == 0 or info.step == trainer.iterations - 1:
            self.bar.set_postfix(stage=info.plan.stage, loss=f"{info.losses['total']:.4f}",
                                 gaussians=info.n_gaussians, refresh=False)

    def on_train_end(self, trainer) -> None:
        self.bar.close()


class LogLines(Callback):
    """One line per `every_s` seconds (and at a frame's start and end) for streams that are not
    a terminal. The ETA is the frame's remaining steps at the rate measured since the last line
    (steps slow down as Gaussians multiply, so the rate since the start would flatter it)."""

    def __init__(self, label: str, every_s: float = 30.0, stream: TextIO | None = None,
                 clock=time.monotonic):
        if not every_s > 0:
            raise ValueError(f"every_s: expected > 0, got {every_s}")
        self.label, self.every_s, self.stream, self.clock = label, every_s, stream, clock
        self.start = self.last = 0.0
        self.last_step = self.start_step = 0

    def _print(self, text: str) -> None:
        print(f"{self.label}: {text}", file=self.stream or sys.stderr, flush=True)

    def on_train_start(self, trainer) -> None:
        self.start = self.last = self.clock()
        self.start_step = self.last_step = trainer.step
        total = trainer.iterations
        self._print(f"{'resumed at' if trainer.step else 'started,'} step {trainer.step}/{total}")

    def on_step_end(self, trainer, info: StepInfo) -> None:
        now, done, total = self.clock(), trainer.step, trainer.iterations
        if now - self.last < self.every_s and done < total:
            return
        rate = (now - self.last) / max(done - self.last_step, 1)
        eta = "" if done >= total else f", ETA {tqdm.format_interval(rate * (total - done))}"
        self._print(f"step {done}/{total} stage {info.plan.stage} loss "
                    f"{info.losses['total']:.4f} gaussians {info.n_gaussians} "
                    f"({rate:.2f} s/step{eta})")
        self.last, self.last_step = now, done

    def on_train_end(self, trainer) -> None:
        steps = trainer.step - self.start_step
        took = tqdm.format_interval(self.clock() - self.start)
        self._print(f"trained {steps} step(s) in {took}")
