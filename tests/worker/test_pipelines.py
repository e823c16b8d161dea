"""worker.pipelines: a reconstruction's parameters resolve to the run configuration the worker
will run with (the same `core.config.load_config` the CLI uses)."""

from __future__ import annotations

import pytest

from core.config import CameraSplit, ResolvedRun, Views, load_config, validate
from worker.pipelines import PIPELINES, ReconstructParams


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
    assert params.run_config() is cfg  # the API's checks and its resolution share it
    with pytest.raises(ValueError, match="frozen"):  # so it cannot go stale
        params.gop = 3
    assert (cfg.gop, cfg.checkpoint_every, cfg.train.seed) == (2, 9, 3)
    # The worker's params come back from the job's stored JSON and resolve to the same.
    stored = ReconstructParams.model_validate(params.model_dump(mode="json"))
    assert stored.run_config() == cfg
    from core.pipeline import reconstruct  # lazy: torch, which this module needs nowhere else

    resolved = ResolvedRun("test", "cap_x", ("000000",), cfg,
                           Views(CameraSplit("none", ("cam00",))))
    with pytest.raises(ValueError, match="not both"):
        reconstruct(tmp_path / "capture", tmp_path / "run", resolved=resolved, gop=3)
    assert not (tmp_path / "run").exists()


def test_the_bounds_are_the_configurations_own():
    """`gop`, `checkpoint_every` and `preset` are checked by the same types as RunConfig's."""
    for name, bad in (("gop", 10_001), ("checkpoint_every", 0), ("preset", "huge")):
        with pytest.raises(ValueError) as err:
            validate(ReconstructParams, {name: bad}, "params")
        assert err.value.details[0]["path"] == f"params.{name}"
        with pytest.raises(ValueError):
            load_config(**({"preset": bad} if name == "preset" else
                           {"overrides": {name: bad}}))


def test_each_pipeline_lists_the_kinds_of_what_it_writes():
    from core.rundir import classify

    written = {  # docs/design.md 3.3, docs/stream.md
        "reconstruct": ["frames/000000/gaussians.ply", "meshes/000000.ply", "meshes/000000.glb",
                        "renders/000000/cam00_rgb.png", "renders/000000/cam00_normal.png",
                        "renders/000000/cam00_ao.png", "renders/000000/cam00_depth.npy",
                        "renders/000000/cam00_relit.png", "plots/loss.png", "config.json",
                        "metrics.json", "sequence.json", "eval.json", "contact_sheet.png"],
        "relight": ["relit/000000/cam00.png", "relit/000000/cam00.exr", "relit/000000.mp4",
                    "relit/videos/cam00.mp4", "relit/relight.json"],
        "export": ["export/stream.dgss", "export/spz/000000.spz", "export/ply/000000.ply",
                   "export/export.json"],
    }
    for name, paths in written.items():
        assert {classify(p).kind for p in paths} == set(PIPELINES[name].artifacts), name
    assert {"mesh", "normal", "ao"} <= set(PIPELINES["reconstruct"].artifacts)


def test_a_pipeline_is_registered_in_one_place():
    """What submits a job of each pipeline and what runs it on a worker are its `PIPELINES`
    entry's: the router and the runner name no pipeline."""
    import importlib
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    for pipeline in PIPELINES.values():
        module, name = pipeline.execution.split(":")
        assert callable(getattr(importlib.import_module(module), name).run), pipeline.name
        assert pipeline.endpoint.startswith("/v1/"), pipeline.name
        for where in ("worker/runner.py", "service/routers/jobs.py"):
            assert f'"{pipeline.name}"' not in (root / where).read_text(), (where, pipeline.name)
