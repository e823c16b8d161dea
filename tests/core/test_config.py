"""core.config: the typed run configuration. Presets, overrides that name every bad setting by
its path (unknown keys, wrong types, NaN and infinity, bounds, checks across fields), the JSON
Schema the API publishes, frame selection, and that none of it imports torch."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest

from core.config import (
    ConfigError,
    MeshConfig,
    RunConfig,
    Schedule,
    apply_overrides,
    load_config,
    parse_frames,
    preset_config,
    schema,
    validate,
)


def _problem(overrides: dict, preset: str = "fast") -> dict:
    with pytest.raises(ConfigError) as err:
        load_config(preset, overrides=overrides)
    assert isinstance(err.value, ValueError)  # callers that catch ValueError keep working
    return err.value.details[0]


def test_presets_and_overrides():
    cfg = preset_config("test")
    assert cfg.checkpoint_every == 100 and cfg.train.schedule.iterations == 500
    assert cfg.mesh.resolution == 128 and preset_config("paper").checkpoint_every == 1000
    out = apply_overrides(cfg, {"train": {"background": [1, 1, 1], "eps2d": 0}})
    assert out.train.background == (1.0, 1.0, 1.0) and isinstance(out.train.eps2d, float)
    assert out.train.schedule == cfg.train.schedule  # untouched sections stay
    assert apply_overrides(cfg, {"sequence": {"motion_candidates": []}}).sequence \
        .motion_candidates == ()
    out = apply_overrides(cfg, {"sequence": {"motion_candidates": [1, 0.25, 0.5]}})
    assert out.sequence.motion_candidates == (1.0, 0.25, 0.5)
    assert all(isinstance(a, float) for a in out.sequence.motion_candidates)
    assert load_config("fast", gop=3).gop == 3
    assert load_config("fast", overrides={"mesh": {"formats": ["obj", "glb"]}}).mesh.formats \
        == ("obj", "glb")


@pytest.mark.parametrize("overrides, path, words", [
    ({"train": {"iters": 3}}, "config.train.iters", "unknown setting (known: antialiased"),
    ({"preset": "fast"}, "config.preset", "unknown setting"),
    ({"train": {"init_points": "many"}}, "config.train.init_points", "valid integer"),
    ({"train": {"init_points": "5"}}, "config.train.init_points", "valid integer"),
    ({"train": {"init_points": 0}}, "config.train.init_points", "greater than or equal to 1"),
    ({"train": {"init_points": 1e400}}, "config.train.init_points", "valid integer"),
    ({"train": {"eps2d": float("nan")}}, "config.train.eps2d", "finite number"),
    ({"train": {"eps2d": float("inf")}}, "config.train.eps2d", "finite number"),
    ({"train": {"schedule": {"iterations": 0}}}, "config.train.schedule.iterations",
     "greater than or equal to 3"),
    ({"train": {"schedule": {"iterations": -5}}}, "config.train.schedule.iterations",
     "greater than or equal to 3"),
    ({"train": {"schedule": {"iterations": 10**12}}}, "config.train.schedule.iterations",
     "less than or equal to 300000"),
    ({"train": {"schedule": {"iterations": 2000}}}, "config.train.schedule",
     "stage2_start, stage3_start"),
    ({"train": {"bake_ao": 1}}, "config.train.bake_ao", "valid boolean"),
    ({"gop": True}, "config.gop", "valid integer"),
    ({"checkpoint_every": None}, "config.checkpoint_every", "valid integer"),
    ({"train": {"background": [1, 1]}}, "config.train.background[2]", "required"),
    ({"train": {"device": "gpu"}}, "config.train.device", "expected auto, cpu, cuda or cuda:N"),
    ({"train": 5}, "config.train", "object"),
    ({"train": {"densify": {"max_gaussians": 2.5}}}, "config.train.densify.max_gaussians",
     "integer"),
    ({"sequence": {"motion_candidates": [0.5, "fast"]}},
     "config.sequence.motion_candidates[1]", "valid number"),
    ({"sequence": {"motion_candidates": 0.5}}, "config.sequence.motion_candidates",
     "valid array"),
    ({"sequence": {"second_order": [1.5]}}, "config.sequence.second_order[0]",
     "less than or equal to 1"),
    ({"sequence": {"deform_retries": 1}}, "config.sequence.deform_retries",
     "unknown setting"),
    ({"mesh": {"formats": ["stl"]}}, "config.mesh.formats[0]", "'ply', 'obj' or 'glb'"),
    ({"mesh": {"resolution": 10**6}}, "config.mesh.resolution", "less than or equal to 2048"),
    ({"train": {"ao": {"n_dirs": 0}}}, "config.train.ao.n_dirs", "greater than or equal to 1"),
])
def test_every_bad_setting_is_named(overrides, path, words):
    problem = _problem(overrides)
    assert problem["path"] == path and words in problem["message"], problem


def test_optional_fields_take_none_or_their_type():
    fast = preset_config("fast")
    assert fast.train.densify.max_gaussians is None
    out = apply_overrides(fast, {"train": {"densify": {"max_gaussians": 9000,
                                                       "prune_scale": None}}})
    assert out.train.densify.max_gaussians == 9000 and out.train.densify.prune_scale is None
    back = apply_overrides(out, {"train": {"densify": {"max_gaussians": None,
                                                       "prune_scale": 1}}})
    assert back.train.densify.max_gaussians is None and back.train.densify.prune_scale == 1.0
    assert apply_overrides(fast, {"normal_estimator": "m.pt"}).normal_estimator == "m.pt"


def test_every_problem_is_listed_and_files_are_named(tmp_path: Path):
    with pytest.raises(ConfigError) as err:
        load_config("fast", overrides={"gop": 0, "train": {"seed": -1, "nope": 1}})
    assert sorted(d["path"] for d in err.value.details) == \
        ["config.gop", "config.train.nope", "config.train.seed"]
    assert "(+2 more)" in str(err.value)
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ConfigError, match="cannot read bad.json") as err:
        load_config("test", bad)
    assert str(tmp_path) not in str(err.value)  # the file, not where it lives
    bad.write_text(json.dumps({"train": {"seed": "x"}}))
    with pytest.raises(ConfigError, match=r"^bad.json.train.seed: "):
        load_config("test", bad)
    with pytest.raises(ConfigError, match="preset: expected one of paper, fast, test"):
        load_config("huge")
    with pytest.raises(ConfigError, match="config: expected a JSON object"):
        apply_overrides(preset_config("fast"), [1])


def test_sections_validate_when_built_and_replaced():
    with pytest.raises(ValueError, match="iterations"):
        Schedule(iterations=2)
    with pytest.raises(ValueError, match="stage2_start"):
        dataclasses.replace(Schedule(), stage2_start=0)
    with pytest.raises(ValueError):
        MeshConfig(formats=["ply"])  # in Python a tuple, as the type says
    assert validate(MeshConfig, {"formats": ["glb"]}).formats == ("glb",)
    with pytest.raises(ConfigError, match=r"^resolution: "):
        validate(MeshConfig, {"resolution": 8})


def test_schema_describes_every_setting_with_its_bounds():
    s = schema(RunConfig)
    defs = s["$defs"]
    iterations = defs["Schedule"]["properties"]["iterations"]
    assert iterations["minimum"] == 3 and iterations["maximum"] == 300_000
    assert iterations["description"] and iterations["default"] == 30_000
    assert s["additionalProperties"] is False
    assert set(s["properties"]) == {f.name for f in dataclasses.fields(RunConfig)}
    for name, section in defs.items():
        assert section.get("additionalProperties") is False, name
        assert not section.get("required"), name  # any subset of the keys is an override
        for key, prop in section["properties"].items():
            assert prop.get("description"), f"{name}.{key} has no description"
            assert "default" in prop or "$ref" in prop, f"{name}.{key} has no default"
    # Every default validates, and the defaults are the dataclasses' own.
    assert validate(RunConfig, {}) == RunConfig()


def test_parse_frames():
    frames = ["a", "b", "c", "d"]
    assert parse_frames(None, frames) == frames
    assert parse_frames("1:3", frames) == ["b", "c"]
    assert parse_frames(":2", frames) == ["a", "b"]
    assert parse_frames("-1:", frames) == ["d"]
    assert parse_frames("0:4:2", frames) == ["a", "c"]
    assert parse_frames("2", frames) == ["c"]
    for bad in ("x:y", "5:9", "1:2:3:4", "7", "::0"):
        with pytest.raises(ValueError, match="frames"):
            parse_frames(bad, frames)


def test_the_configuration_imports_no_torch():
    code = ("import sys, core.config; core.config.load_config('paper'); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"
