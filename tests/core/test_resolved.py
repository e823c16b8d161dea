"""core.config.resolved: the record of a resolved run. It round-trips through RUN/config.json,
a version 1 config.json as the code wrote it before the record existed upgrades to the run it
described, the rig's near plane is resolved into it and travels with it, and resolving it
refuses what the capture cannot run (the rules the API's door uses
too); and the grouping of frames the API splits a job by and the run plans with."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from core.config import (
    CONFIG_VERSION,
    ConfigError,
    ResolvedRun,
    independent_groups,
    load_config,
    read_run,
    resolve_run,
    segment,
    upgrade,
)
from core.data.capture import Camera, Capture
from core.sequence import GopPlan
from core.synth import SynthConfig, synthesize

# tests/data/config-v1.json is the config.json that `reconstruct` wrote for a service job
# (capture named by id) before this record existed: preset test, frames 0:2, gop 2, split
# every8, downscale 2, train.seed 3, on the CPU; of this capture.
V1 = Path(__file__).resolve().parents[1] / "data" / "config-v1.json"
V1_CAPTURE = SynthConfig(frames=3, views=9, width=24, height=24, seed=4)


@pytest.fixture(scope="module")
def v1_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("v1") / "capture"
    synthesize(out, V1_CAPTURE)
    return out


def _capture(cameras: int, test_cameras: tuple[str, ...] | None = None) -> Capture:
    """An in-memory capture of `cameras` cameras (no files: nothing here opens one)."""
    K = np.array([[20.0, 0, 12], [0, 20, 12], [0, 0, 1]])
    cams = tuple(Camera(f"cam{i:02d}", 24, 24, K, np.eye(4)) for i in range(cameras))
    return Capture(Path("/nowhere"), cams, ("000000", "000001"), (0.0, 0.0, 1.0),
                   test_cameras=test_cameras)


def test_the_record_round_trips_through_config_json(tmp_path: Path):
    config = load_config("test", overrides={"split": "none", "downscale": 2.0, "gop": 3,
                                            "train": {"seed": 5, "masks": "subject"}})
    run = resolve_run(_capture(3), config, preset="test", frames="1:", capture_name="cap_x")
    assert run.frames == ("000001",) and run.capture == "cap_x"
    assert run.views.split.training == ("cam00", "cam01", "cam02") and run.views.subject
    assert run.views.downscale == 2.0 and run.views.split.heldout == ()
    data = run.to_json()
    assert data["version"] == CONFIG_VERSION and data["config"]["train"]["seed"] == 5
    (tmp_path / "config.json").write_text(json.dumps(data))
    back = read_run(tmp_path)
    assert back == run and back.to_json() == data
    assert isinstance(back.frames, tuple) and isinstance(back.config.train.background, tuple)
    with pytest.raises(ConfigError) as err:  # a damaged record names the field
        ResolvedRun.from_json({**data, "views": {**data["views"], "masks": "both"}})
    assert err.value.details[0]["path"] == "config.json.views.masks"


def test_a_version_1_config_json_upgrades_to_the_run_it_described(v1_capture: Path,
                                                                 tmp_path: Path):
    old = json.loads(V1.read_text())
    assert old["version"] == 1 and old["split"] == "every8"  # the file as it was written
    with pytest.raises(ValueError, match="pass the capture folder"):
        upgrade(old)  # it names the capture by id: its views need the capture
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    shutil.copyfile(V1, run_dir / "config.json")
    run = read_run(run_dir, v1_capture)
    assert (run.preset, run.capture, run.frames) == ("test", old["capture"],
                                                     ("000000", "000001"))
    expected = load_config("test", overrides={"split": "every8", "downscale": 2.0,
                                              "train": {"seed": 3, "near": 0.01, "schedule": {
                                                  "densify_epoch": False}, "losses": {
                                                  "normal_confidence": "per_view"}}}, gop=2)
    assert run.config == run.on_device("cpu").config and run.config.train.device == "cpu"
    assert dataclasses.replace(expected, train=dataclasses.replace(
        expected.train, device="cpu")) == run.config
    assert run.views.split.rule == "every8" and run.views.split.heldout == ("cam00", "cam08")
    assert run.views.downscale == 2.0 and run.views.masks == "matte"
    # The run it describes is the one the same request resolves to now (with the near plane
    # every render had then): a job stored before the record existed resumes its old run
    # directory.
    from core.data import load_capture

    now = resolve_run(load_capture(v1_capture), expected, preset="test", frames="0:2",
                      capture_name=old["capture"])
    assert now.same_run(run) and now.frames == run.frames
    assert upgrade(run.to_json()) == run.to_json()  # the current version as it is


def test_a_version_3_record_keeps_the_densification_interval_it_ran_at(tmp_path: Path):
    """Version 3 records predate `densify_epoch`: they upgrade with it off, the interval
    their runs densified at, and keep everything else (the near plane they resolved)."""
    run = resolve_run(_capture(3), load_config("test", overrides={
        "split": "none", "train": {"seed": 5}}), preset="test")
    data = run.to_json()
    assert data["config"]["train"]["schedule"]["densify_epoch"] is True  # today's default
    del data["config"]["train"]["schedule"]["densify_epoch"]
    old = {**data, "version": 3}
    new = upgrade(old)
    assert new["version"] == CONFIG_VERSION
    assert new["config"]["train"]["schedule"]["densify_epoch"] is False
    assert new["config"]["train"]["losses"]["normal_confidence"] == "per_view"
    assert new["config"]["train"]["near"] == data["config"]["train"]["near"]
    back = ResolvedRun.from_json(old)
    assert back.config.train.schedule.densify_epoch is False
    assert back.config.train.seed == 5


def test_a_version_4_record_keeps_how_its_priors_confidences_weighed():
    """Version 4 records predate `normal_confidence`: they upgrade with `per_view`, the
    weighing their runs trained with, and keep the densification interval they recorded."""
    run = resolve_run(_capture(3), load_config("test", overrides={
        "split": "none", "train": {"seed": 5}}), preset="test")
    data = run.to_json()
    data["config"]["train"]["losses"]["normal_confidence"] = "absolute"  # as a run may set it
    assert ResolvedRun.from_json(data).config.train.losses.normal_confidence == "absolute"
    del data["config"]["train"]["losses"]["normal_confidence"]
    old = {**data, "version": 4}
    new = upgrade(old)
    assert new["version"] == CONFIG_VERSION
    assert new["config"]["train"]["losses"]["normal_confidence"] == "per_view"
    assert new["config"]["train"]["schedule"]["densify_epoch"] is True  # as version 4 had it
    assert ResolvedRun.from_json(old).config.train.losses.normal_confidence == "per_view"


def test_an_unknown_version_is_refused_naming_it():
    with pytest.raises(ConfigError, match="version 7 is not one this code reads"):
        upgrade({"version": 7})


@pytest.mark.parametrize("split", ["auto", "every8"])
def test_a_split_that_leaves_nothing_to_train_is_refused(split):
    config = load_config("test", overrides={"split": split})
    with pytest.raises(ConfigError) as err:
        resolve_run(_capture(1), config, preset="test")
    assert err.value.details[0]["path"] == "config.split"
    assert "every8 leaves no camera to train on" in err.value.details[0]["message"]
    none = resolve_run(_capture(1), load_config("test", overrides={"split": "none"}),
                       preset="test")
    assert none.views.split.scored == ("cam00",)


def test_a_subject_mesh_needs_masks():
    config = load_config("test", overrides={"mesh": {"subject": True}})
    with pytest.raises(ConfigError) as err:  # no mask file in the (file-less) capture
        resolve_run(_capture(9), config, preset="test")
    assert err.value.details[0]["path"] == "config.mesh.subject"
    assert "has no masks" in err.value.details[0]["message"]
    with pytest.raises(ConfigError):
        resolve_run(_capture(9), config, preset="test", has_masks=False)
    assert resolve_run(_capture(9), config, preset="test", has_masks=True).config.mesh.subject


def test_declared_test_cameras_are_held_out_and_frames_are_named():
    run = resolve_run(_capture(4, ("cam02",)), load_config("test"), preset="test")
    assert run.views.split.rule == "capture" and run.views.split.heldout == ("cam02",)
    with pytest.raises(ConfigError) as err:
        resolve_run(_capture(4), load_config("test"), preset="test", frames="5:9")
    assert err.value.details[0]["path"] == "frames"


def test_a_sequence_splits_into_its_groups_of_pictures():
    frames = [f"{i:06d}" for i in range(7)]
    cfg = load_config("test", gop=3)
    groups = independent_groups(frames, cfg)
    assert [list(g.frames) for g in groups] == [frames[0:3], frames[3:6], frames[6:7]]
    assert [g.frames for g in groups] == [g.frames for g in segment(frames, 3)]
    # Groups that spend each other's refine balance cannot run apart.
    run_scope = dataclasses.replace(cfg, sequence=dataclasses.replace(cfg.sequence,
                                                                      refine_scope="run"))
    assert independent_groups(frames, run_scope) is None
    # Independent frames: one group per frame, as the plan of the run has them.
    off = dataclasses.replace(cfg, sequence=dataclasses.replace(cfg.sequence, enabled=False))
    assert [g.frames for g in independent_groups(frames[:3], off)] == [(f,) for f in frames[:3]]
    assert GopPlan(frames[:3], 3, off.sequence, 500).gop == 1


def _ring(cameras: int, radius: float) -> Capture:
    """An in-memory capture of `cameras` cameras on a horizontal circle of `radius` about the
    origin, each looking at it."""
    K = np.array([[20.0, 0, 12], [0, 20, 12], [0, 0, 1]])
    cams = []
    for i in range(cameras):
        a = 2 * np.pi * i / cameras
        centre = radius * np.array([np.cos(a), 0.0, np.sin(a)])
        z = -centre / radius
        x = np.cross([0.0, 1.0, 0.0], z)
        R = np.stack([x, np.cross(z, x), z])
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ centre
        cams.append(Camera(f"cam{i:02d}", 24, 24, K, w2c))
    return Capture(Path("/nowhere"), tuple(cams), ("000000",), (0.0, 1.0, 0.0))


def test_a_forward_facing_rig_keeps_its_near_plane_within_its_spread():
    # Five cameras 0.5 apart on a line, toed in to meet 100 away: the point they look at is far
    # beyond any scene they film, so their spread bounds the plane.
    cams = []
    for i, x in enumerate(np.linspace(-1.0, 1.0, 5)):
        z = np.array([-x, 0.0, 100.0]) / np.hypot(x, 100.0)
        xa = np.cross([0.0, 1.0, 0.0], z)
        R = np.stack([xa, np.cross(z, xa), z])
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ np.array([x, 0.0, 0.0])
        cams.append(Camera(f"cam{i:02d}", 24, 24, np.diag([20.0, 20.0, 1.0]), w2c))
    capture = Capture(Path("/nowhere"), tuple(cams), ("000000",), (0.0, 1.0, 0.0))
    near = resolve_run(capture, load_config("test"), preset="test").config.train.near
    assert near == pytest.approx(0.2 * 2 * 0.5)


def test_the_rigs_near_plane_is_resolved_into_the_record_and_travels(tmp_path: Path):
    config = load_config("test")
    assert config.train.near is None  # the rig's, resolved with the run
    run = resolve_run(_ring(8, 5.0), config, preset="test")
    assert run.config.train.near == pytest.approx(1.0)  # a fifth of the cameras' distance
    (tmp_path / "config.json").write_text(json.dumps(run.to_json()))
    back = read_run(tmp_path)
    assert back.config.train.near == run.config.train.near and back.same_run(run)
    given = load_config("test", overrides={"train": {"near": 0.2}})
    assert resolve_run(_ring(8, 5.0), given, preset="test").config.train.near == 0.2
    assert not resolve_run(_ring(8, 5.0), given, preset="test").same_run(run)
    with pytest.raises(ConfigError) as err:
        load_config("test", overrides={"train": {"near": 0}})
    assert err.value.details[0]["path"] == "config.train.near"
    # A version 2 record, from before runs recorded it, rendered at the rasterizer's 0.01.
    old = run.to_json()
    del old["config"]["train"]["near"]
    assert upgrade({**old, "version": 2})["config"]["train"]["near"] == 0.01
    assert ResolvedRun.from_json({**old, "version": 2}).config.train.near == 0.01


def test_the_stages_after_training_render_at_the_runs_near_plane(v1_capture: Path,
                                                                   tmp_path: Path):
    from core.data import load_capture
    from core.relight.gbuffer import run_render

    capture = load_capture(v1_capture)
    config = load_config("test")
    run = resolve_run(capture, config, preset="test")
    assert config.train.near is None and run.config.train.near > 0.01
    (tmp_path / "config.json").write_text(json.dumps(run.to_json()))
    settings = run_render(tmp_path, v1_capture)
    assert settings.near == run.config.train.near
    assert settings.camera(capture.cameras[0]).near == settings.near
