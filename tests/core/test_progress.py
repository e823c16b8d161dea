"""Progress on the command line away from a terminal: timed lines with an ETA (core.progress)."""

from __future__ import annotations

import io
from types import SimpleNamespace

import pytest

from core.progress import LogLines


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _info(step: int, stage: int = 1, loss: float = 0.5, gaussians: int = 1000):
    return SimpleNamespace(step=step, plan=SimpleNamespace(stage=stage),
                           losses={"total": loss}, n_gaussians=gaussians)


def _trainer(step: int = 0, iterations: int = 100):
    return SimpleNamespace(step=step, iterations=iterations)


def test_lines_come_on_the_interval_with_the_recent_rate() -> None:
    clock, out = _Clock(), io.StringIO()
    lines = LogLines("frame 000000 (1/1)", every_s=30, stream=out, clock=clock)
    trainer = _trainer()
    lines.on_train_start(trainer)
    for step in range(100):
        # 0.5 s a step for the first 60 steps, then 2 s a step: the ETA follows the recent rate.
        clock.now += 0.5 if step < 60 else 2.0
        trainer.step = step + 1
        lines.on_step_end(trainer, _info(step, stage=1 if step < 50 else 2, loss=1 / (step + 1)))
    lines.on_train_end(trainer)
    got = out.getvalue().splitlines()
    assert got[0] == "frame 000000 (1/1): started, step 0/100"
    assert got[1] == ("frame 000000 (1/1): step 60/100 stage 2 loss 0.0167 gaussians 1000 "
                      "(0.50 s/step, ETA 00:20)")
    assert got[2] == ("frame 000000 (1/1): step 75/100 stage 2 loss 0.0133 gaussians 1000 "
                      "(2.00 s/step, ETA 00:50)")
    # The last step always prints, without an ETA.
    assert got[-2].startswith("frame 000000 (1/1): step 100/100 stage 2 loss 0.0100")
    assert "ETA" not in got[-2]
    assert got[-1] == "frame 000000 (1/1): trained 100 step(s) in 01:50"
    assert len(got) == 6  # start, lines at steps 60, 75, 90 and 100, end


def test_a_resumed_frame_says_where_it_resumed() -> None:
    clock, out = _Clock(), io.StringIO()
    lines = LogLines("frame 000003 (4/5)", stream=out, clock=clock)
    trainer = _trainer(step=40, iterations=90)
    lines.on_train_start(trainer)
    clock.now += 12
    trainer.step = 90
    lines.on_train_end(trainer)
    assert out.getvalue().splitlines() == ["frame 000003 (4/5): resumed at step 40/90",
                                           "frame 000003 (4/5): trained 50 step(s) in 00:12"]


def test_interval_must_be_positive() -> None:
    with pytest.raises(ValueError, match="every_s"):
        LogLines("x", every_s=0)
