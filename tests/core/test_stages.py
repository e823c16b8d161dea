"""The pure step -> stage schedule: paper boundaries, beta ramp, SH, densify/reset timing, presets."""

from __future__ import annotations

import math

import pytest

from core.config import PRESETS, Schedule, schedule_for
from core.stages import plan


def test_paper_stage_boundaries_and_flags():
    s = schedule_for("paper")
    p = plan(0, s)
    assert (p.stage, p.beta, p.sh_degree, p.tie_opacity, p.geometry_branch) == (1, 0.0, 0, True,
                                                                                 False)
    assert not (p.normal_prior or p.consistency or p.visibility)
    assert plan(6_999, s).stage == 1 and plan(6_999, s).beta == 0.0
    p = plan(7_000, s)
    assert p.stage == 2 and p.start_geometry and p.geometry_branch and not p.tie_opacity
    assert p.normal_prior and p.consistency and not p.visibility and p.sh_degree == 0
    assert not plan(7_001, s).start_geometry
    p = plan(21_000, s)
    assert p.stage == 3 and p.bake_ao and p.visibility and p.sh_degree == 1
    assert [plan(k, s).bake_ao for k in range(30_000)].count(True) == 1
    assert [plan(k, s).start_geometry for k in range(30_000)].count(True) == 1
    assert plan(22_000, s).sh_degree == 2 and plan(23_000, s).sh_degree == 3
    assert plan(29_999, s).sh_degree == 3


def test_sh_from_the_start_rises_as_3dgs_and_leaves_the_stages_alone():
    paper, early = schedule_for("paper"), Schedule(sh_from="start")
    assert [plan(k, early).sh_degree for k in (0, 999, 1_000, 2_000, 3_000, 29_999)] == \
        [0, 0, 1, 2, 3, 3]
    assert [plan(k, early, "3dgs").sh_degree for k in (0, 1_000, 2_000, 3_000)] == [0, 1, 2, 3]
    for k in (0, 6_999, 7_000, 21_000, 29_999):  # everything else as the paper's
        a, b = plan(k, paper), plan(k, early)
        assert (a.stage, a.beta, a.bake_ao, a.start_geometry, a.densify, a.reset_opacity) == \
            (b.stage, b.beta, b.bake_ao, b.start_geometry, b.densify, b.reset_opacity)
    assert plan(7_000, paper).sh_degree == 0 and plan(7_000, early).sh_degree == 3
    assert Schedule(sh_from="start").scaled(600).sh_from == "start"
    with pytest.raises(ValueError, match="sh_from"):
        Schedule(sh_from="later")


def test_beta_cosine_ramp_reaches_max_at_the_end():
    s = schedule_for("paper")
    betas = [plan(k, s).beta for k in range(7_000, 30_000)]
    assert betas[0] == 0.0
    assert betas[-1] == pytest.approx(0.7)
    assert all(b2 >= b1 for b1, b2 in zip(betas, betas[1:]))
    mid = plan(7_000 + (29_999 - 7_000) // 2, s).beta
    assert mid == pytest.approx(0.35, abs=1e-3)
    quarter = plan(7_000 + round((29_999 - 7_000) / 4), s).beta
    assert quarter == pytest.approx(0.7 * 0.5 * (1 - math.cos(math.pi / 4)), abs=1e-3)


def test_densify_and_reset_follow_3dgs():
    s = schedule_for("paper")
    dens = [k for k in range(30_000) if plan(k, s).densify]
    assert dens[0] == 600 and dens[-1] == 14_900 and all(k % 100 == 0 for k in dens)
    resets = [k for k in range(30_000) if plan(k, s).reset_opacity]
    assert resets == [3_000, 6_000, 9_000, 12_000]


@pytest.mark.parametrize("name", ["fast", "test"])
def test_presets_scale_the_plan(name: str):
    s = PRESETS[name]
    f = s.iterations / 30_000
    assert s.stage2_start == round(7_000 * f) and s.stage3_start == round(21_000 * f)
    assert s.densify_until == round(15_000 * f) and s.reset_interval == round(3_000 * f)
    assert s.densify_interval == max(1, round(100 * f))
    stages = [plan(k, s).stage for k in range(s.iterations)]
    assert stages.count(1) == s.stage2_start
    assert stages.count(3) == s.iterations - s.stage3_start
    assert plan(s.iterations - 1, s).beta == pytest.approx(0.7)
    assert plan(s.iterations - 1, s).sh_degree == 3
    resets = [k for k in range(s.iterations) if plan(k, s).reset_opacity]
    assert len(resets) == 4


def test_test_preset_is_short():
    assert 200 <= PRESETS["test"].iterations <= 1000


def test_bad_arguments_name_themselves():
    with pytest.raises(ValueError, match="step"):
        plan(30_000, Schedule())
    with pytest.raises(ValueError, match="step"):
        plan(-1, Schedule())
    with pytest.raises(ValueError, match="stage2_start"):
        Schedule(stage2_start=22_000)
    with pytest.raises(ValueError, match="beta_max"):
        Schedule(beta_max=1.5)
    with pytest.raises(ValueError, match="preset"):
        schedule_for("slow")
    with pytest.raises(ValueError, match="iterations"):
        Schedule().scaled(2)
