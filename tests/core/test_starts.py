"""The deform stage's start race (core.sequence.starts): which views it scores in which order,
when a rival is dropped, when the race goes on to every view, and what it costs."""

from __future__ import annotations

import math

import pytest
import torch

from core.sequence.starts import VIEWS_PER_ROUND, race_starts, view_order


def _ring(count: int) -> torch.Tensor:
    a = torch.arange(count, dtype=torch.float64) * 2 * math.pi / count
    return torch.stack([torch.cos(a), torch.sin(a), torch.zeros_like(a)], dim=-1)


def test_views_come_in_farthest_point_order():
    order = view_order(_ring(8))
    assert sorted(order) == list(range(8)) and order[:2] == [0, 4]
    assert set(order[2:4]) == {2, 6}  # the two quarter points, then the odd ones
    # Each view is the farthest (in centre distance) from those before it.
    c = _ring(8)
    for k in range(1, 8):
        gaps = {v: min(float((c[v] - c[u]).norm()) for u in order[:k])
                for v in range(8) if v not in order[:k]}
        assert gaps[order[k]] == pytest.approx(max(gaps.values()))
    # A line of cameras: the far end next, then the middle.
    line = torch.tensor([[float(i), 0.0, 0.0] for i in range(5)])
    assert view_order(line)[:3] == [0, 4, 2]
    assert view_order(torch.zeros(0, 3)) == []
    assert sorted(view_order(torch.zeros(3, 3))) == [0, 1, 2]  # coinciding: each view once
    with pytest.raises(ValueError, match="centres"):
        view_order(torch.zeros(4, 2))


def _table(rows: dict[str, list[float]]):
    calls = []

    def loss(name: str, view: int) -> float:
        calls.append((name, view))
        return rows[name][view]

    return loss, calls


def test_a_clear_loser_is_dropped_after_the_first_views():
    rows = {"rest": [1.0, 1.1, 0.9, 1.2, 1.0, 1.0, 1.0, 1.0],
            "damped 1": [0.5, 0.6, 0.4, 0.55, 9.0, 9.0, 9.0, 9.0]}
    loss, calls = _table(rows)
    race = race_starts(list(rows), loss, list(range(8)), first=4, t_stop=2.0)
    assert race.order == ["damped 1", "rest"]
    assert race.views == {"rest": 4, "damped 1": 4} and race.renders == 8
    assert len(calls) == len(set(calls)) == 8  # no view scored twice
    assert race.scores["damped 1"] == pytest.approx(sum(rows["damped 1"][:4]) / 4)


def test_a_close_race_goes_on_until_the_evidence_separates_the_starts():
    """The frame-22 case: on the first four views one start leads, over every view the other."""
    views = list(range(14))
    a = [0.040, 0.063, 0.042, 0.029, 0.031, 0.034, 0.047, 0.050, 0.033, 0.039, 0.029, 0.026,
         0.032, 0.028]
    b = [0.062, 0.039, 0.030, 0.032, 0.039, 0.033, 0.033, 0.043, 0.023, 0.033, 0.035, 0.024,
         0.032, 0.030]
    order = [0, 4, 7, 10, 13, 2, 12, 1, 3, 5, 6, 8, 9, 11]
    rows = {"rest": [a[v] for v in order], "damped 1": [b[v] for v in order]}
    assert sum(rows["rest"][:4]) < sum(rows["damped 1"][:4])  # four views: rest
    assert sum(a) > sum(b)  # every view: damped
    loss, calls = _table(rows)
    race = race_starts(list(rows), loss, views, first=4, t_stop=2.0)
    assert race.order[0] == "damped 1"
    assert race.views == {"rest": 14, "damped 1": 14} and len(calls) == 28
    # Without the race (t_stop 0) the first four views decide, as before.
    loss, calls = _table(rows)
    quick = race_starts(list(rows), loss, views, first=4, t_stop=0.0)
    assert quick.order == ["rest", "damped 1"] and quick.renders == 8 == len(calls)


def test_three_starts_race_in_rounds_and_the_order_ranks_the_dropped_last():
    n = 10
    rows = {"rest": [5.0 + 0.1 * (v % 2) for v in range(n)],  # far behind: out after 4 views
            "damped 1": [1.0 + (0.3 if v % 2 else -0.3) for v in range(n)],
            "second-order 0.5": [1.0 + (-0.29 if v % 2 else 0.31) for v in range(n)]}
    loss, calls = _table(rows)
    race = race_starts(list(rows), loss, list(range(n)), first=4, t_stop=2.0)
    assert race.views["rest"] == 4
    # The other two alternate around 1.0 on every view: never separated, scored on all ten,
    # added VIEWS_PER_ROUND at a time.
    assert race.views["damped 1"] == race.views["second-order 0.5"] == n
    assert (n - 4) % VIEWS_PER_ROUND == 0 and race.renders == 4 + 2 * n == len(calls)
    assert race.order[-1] == "rest" and set(race.order[:2]) == {"damped 1", "second-order 0.5"}
    means = {k: sum(v) / n for k, v in rows.items() if k != "rest"}
    assert race.order[0] == min(means, key=means.get)


def test_single_and_identical_starts_cost_nothing_or_the_first_views():
    loss, calls = _table({"rest": [1.0] * 6})
    alone = race_starts(["rest"], loss, list(range(6)), first=4, t_stop=2.0)
    assert alone.order == ["rest"] and alone.renders == 0 and not calls
    rows = {"rest": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0], "damped 1": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]}
    loss, calls = _table(rows)
    same = race_starts(list(rows), loss, list(range(6)), first=4, t_stop=2.0)
    assert same.order == ["rest", "damped 1"] and same.renders == 8  # ties go to the first
    # Fewer views than `first`: every view, once.
    loss, calls = _table(rows)
    few = race_starts(list(rows), loss, [0, 1], first=4, t_stop=2.0)
    assert few.views == {"rest": 2, "damped 1": 2}
    with pytest.raises(ValueError, match="t_stop"):
        race_starts(list(rows), loss, [0, 1], first=4, t_stop=-1.0)
    with pytest.raises(ValueError, match="names"):
        race_starts([], loss, [0, 1], first=4, t_stop=2.0)
