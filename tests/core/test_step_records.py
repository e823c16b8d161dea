"""Step records that stay on the device: `StepInfo` reads its numbers only when asked,
`History` reads them in batches, and a step event always carries a loss, also the first
event of a resumed frame."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from core.metrics import psnr_of_mse
from core.pipeline.events import LOSS_EVERY, History, Hooks
from core.stages import plan
from core.training.callbacks import StepInfo


def _info(step: int) -> StepInfo:
    terms = {"photometric": torch.tensor(0.5 / (step + 1)), "normal": torch.tensor(0.1)}
    terms["total"] = terms["photometric"] + terms["normal"]
    return StepInfo(step, plan(0), terms, 100 + step, 0.01, torch.tensor(1e-3 * (step + 1)))


def test_step_info_reads_its_numbers_as_floats():
    info = _info(3)
    assert info.losses == pytest.approx({"photometric": 0.125, "normal": 0.1, "total": 0.225})
    assert info.psnr == pytest.approx(psnr_of_mse(float(torch.tensor(4e-3))))


def test_history_batches_are_the_step_by_step_records():
    history = History(every=4)
    infos = [_info(i) for i in range(10)]
    for info in infos:
        history.on_step_end(None, info)
    assert len(history._records) == 8 and len(history._pending) == 2  # two reads so far
    records = history.records  # reading flushes the rest
    assert [r["step"] for r in records] == list(range(10))
    for r, info in zip(records, infos):
        assert r == {"step": info.step, "stage": 1, "gaussians": info.n_gaussians,
                     "psnr": info.psnr, "seconds": 0.01, **info.losses}
    history.records = records[:3]  # a resumed frame's records
    history.on_step_end(None, _info(3))
    assert [r["step"] for r in history.records] == [0, 1, 2, 3]


def test_a_resumed_frames_first_step_event_carries_its_loss():
    events = []
    hooks = Hooks("000000", 0, 1, events.append, None)
    trainer = SimpleNamespace(step=0, iterations=100, model=[0] * 5, phase="key", notes=[])
    steps = (LOSS_EVERY * 3 + 7, LOSS_EVERY * 3 + 8, LOSS_EVERY * 4)  # from a checkpoint
    for step in steps:
        trainer.step = step + 1
        hooks.on_step_end(trainer, _info(step))
    losses = [e.loss for e in events]
    assert losses[0] == pytest.approx(_info(steps[0]).losses["total"])
    assert losses[1] == losses[0]  # between reads the last one read
    assert losses[2] == pytest.approx(_info(steps[2]).losses["total"])
