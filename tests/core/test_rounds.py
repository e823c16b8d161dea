"""The deform stage's round bookkeeping (core.sequence.rounds): end losses, when a retry starts,
from which start, which round is kept, and its state through a checkpoint."""

from __future__ import annotations

import pytest
import torch

from core.sequence.rounds import DeformRounds


NAMES = {"rest": 0.0, "damped 0.5": 0.5, "damped 1": 1.0}


def _starts() -> dict:
    return {n: (torch.full((3, 4), a), torch.full((3, 3), 10 * a)) for n, a in NAMES.items()}


SCORES = {"rest": 0.3, "damped 0.5": 0.1, "damped 1": 0.2}


def _run_round(rounds: DeformRounds, losses: list[float], marker: float):
    for x in losses:
        rounds.record(x)
    return rounds.end(torch.full((3, 4), marker), torch.full((3, 3), marker))


def test_starts_follow_the_scores_and_the_end_loss_is_the_last_sixth():
    r = DeformRounds(_starts(), SCORES, 12, reference_loss=None,
                     retries=1, ratio=1.2)
    assert r.order == ["damped 0.5", "damped 1", "rest"] and r.start == "damped 0.5"
    assert torch.equal(r.first()[0], _starts()["damped 0.5"][0])
    end = _run_round(r, [9.0] * 10 + [1.0, 3.0], marker=7.0)  # last 12 // 6 = 2 steps
    assert not end.retry and r.deform_loss == 2.0 and r.kept == 0
    assert torch.equal(end.q, torch.full((3, 4), 7.0))


def test_a_round_behind_the_reference_retries_from_the_next_start_then_keeps_the_best():
    r = DeformRounds(_starts(), SCORES, 6, reference_loss=1.0,
                     retries=2, ratio=1.2)
    first = _run_round(r, [5.0] * 6, marker=1.0)  # 5x the reference: retry
    assert first.retry and r.retries == 1
    assert torch.equal(first.start[0], _starts()["damped 1"][0])  # the second-best start
    assert "start damped 1" in first.note and "5.00x" in first.note
    second = _run_round(r, [1.5] * 6, marker=2.0)  # still 1.5x: the last retry
    assert second.retry and torch.equal(second.start[1], _starts()["rest"][1])
    third = _run_round(r, [3.0] * 6, marker=3.0)  # retries used up: keep the lowest (round 2)
    assert not third.retry and r.kept == 1 and r.deform_loss == 1.5
    assert torch.equal(third.q, torch.full((3, 4), 2.0)) and r.start == "damped 1"


def test_no_reference_or_a_round_under_the_ratio_never_retries():
    r = DeformRounds(_starts(), {}, 6, reference_loss=None, retries=3, ratio=1.2)
    assert not _run_round(r, [100.0] * 6, marker=0.0).retry
    r = DeformRounds(_starts(), {}, 6, reference_loss=1.0, retries=3, ratio=1.2)
    assert not _run_round(r, [1.19] * 6, marker=0.0).retry  # just under 1.2x
    r = DeformRounds({"rest": _starts()["rest"]}, {}, 6, reference_loss=1.0, retries=1,
                     ratio=1.2)
    end = _run_round(r, [1.2] * 6, marker=0.0)  # at 1.2x: retry, no start left
    assert end.retry and end.start is None and "where round 1 ended" in end.note


def test_state_survives_a_checkpoint():
    r = DeformRounds(_starts(), SCORES, 6, reference_loss=1.0,
                     retries=1, ratio=1.2)
    _run_round(r, [5.0] * 6, marker=1.0)
    r.record(0.5)
    copy = DeformRounds(_starts(), SCORES, 6, reference_loss=1.0,
                        retries=1, ratio=1.2)
    copy.load_state_dict(r.state_dict())
    assert (copy.retries, copy.losses, copy.kept) == (1, [0.5], None)
    assert copy.ended[0][0] == 5.0 and torch.equal(copy.ended[0][1], r.ended[0][1])
    with pytest.raises(ValueError, match="scores"):
        DeformRounds({"rest": _starts()["rest"]}, {"damped 0.5": 1.0}, 6, reference_loss=None,
                     retries=0, ratio=1.2)
