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


def test_resolved_once_and_the_same_on_the_worker(tmp_path):
    params = ReconstructParams(preset="test", gop=2, checkpoint_every=9,
                               config={"train": {"seed": 3}})
    cfg = params.run_config()
    assert params.run_config() is cfg  # the API's checks and its split share one resolution
    assert (cfg.gop, cfg.checkpoint_every, cfg.train.seed) == (2, 9, 3)
    # The worker's params come back from the job's stored JSON and resolve to the same.
    stored = ReconstructParams.model_validate(params.model_dump(mode="json"))
    assert stored.run_config() == cfg
    from core.pipeline import reconstruct  # lazy: torch, which this module needs nowhere else

    with pytest.raises(ValueError, match="not both"):
        reconstruct(tmp_path / "capture", tmp_path / "run", config=cfg, gop=3)
    assert not (tmp_path / "run").exists()
