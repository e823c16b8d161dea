"""Rate control of refine steps (core.sequence.budget.refine_steps) by hand: ratio, clip, credit,
the start race's extra renders, floor, and the fixed mode."""

from __future__ import annotations

import pytest

from core.config import SequenceConfig
from core.sequence.budget import refine_steps

SEQ = SequenceConfig(refine_adapt=3.0, refine_min=0.5, refine_max=2.0, refine_second=2.0)


@pytest.mark.parametrize("end, reference, credit, extra, steps", [
    (1.1, 1.0, 100, 0, 13),   # 1.1 ** 3 = 1.33 x the nominal 10
    (10.0, 1.0, 100, 0, 20),  # clipped to refine_max
    (10.0, 1.0, 4, 0, 14),    # at most the nominal plus the credit
    (10.0, 1.0, 4, 3, 11),    # less what the start race took beyond start_views
    (10.0, 1.0, 0, 3, 7),
    (10.0, 1.0, -100, 0, 5),  # deep in debt: the floor (ceil(0.5 x 10))
    (10.0, 1.0, 0, 100, 5),   # a long race cannot push it under the floor either
    (0.1, 1.0, 100, 0, 5),    # far ahead: refine_min
    (1.0, None, 100, 0, 20),  # no reference: refine_second
    (None, 1.0, 100, 5, 10),  # no deform stage ended: the nominal
])
def test_refine_steps(end, reference, credit, extra, steps):
    assert refine_steps(SEQ, 10, end, reference, credit, extra) == steps


def test_fixed_refine_steps_ignore_everything():
    fixed = SequenceConfig(refine_adapt=0.0)
    assert refine_steps(fixed, 10, 10.0, 1.0, -100, 50) == 10
