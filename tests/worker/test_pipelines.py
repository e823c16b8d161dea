"""worker.pipelines: a reconstruction's parameters resolve to the run configuration the worker
will run with (the same `core.config.load_config` the CLI uses)."""

from __future__ import annotations

import pytest

from worker.pipelines import ReconstructParams


def test_top_level_parameters_and_config_agree():
    assert ReconstructParams(config={"gop": 5}).run_config().gop == 5  # not hidden by a default
    assert ReconstructParams(gop=3, config={"gop": 5}).run_config().gop == 3  # the explicit one
    assert ReconstructParams().run_config().gop == 20
    cfg = ReconstructParams(preset="test", checkpoint_every=7).run_config()
    assert cfg.checkpoint_every == 7 and cfg.train.schedule.iterations == 500


def test_a_bad_setting_is_named_under_config():
    with pytest.raises(ValueError) as err:
        ReconstructParams(config={"train": {"schedule": {"iterations": 0}}}).run_config()
    assert err.value.details[0]["path"] == "config.train.schedule.iterations"
