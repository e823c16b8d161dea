"""The Panoptic / Dynamic 3D Gaussians layout: import (auto-detected, one rig checked, the
dataset's test cameras kept, masks as a subject inside the scene), and the camera split that a
capture declares or a run chooses."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from core.data import CaptureError, detect_format, import_capture, load_capture, validate_capture
from core.data.importers.panoptic import export_panoptic
from core.config import camera_split, read_run

TEST_CAMERAS = ["cam00", "cam05"]


@pytest.fixture
def source(synth_capture: Path, tmp_path: Path) -> Path:
    """The tiny synthetic capture (8 cameras, 2 frames) written in the Panoptic layout."""
    out = tmp_path / "panoptic"
    export_panoptic(load_capture(synth_capture), out, test_cameras=TEST_CAMERAS)
    return out


def test_import_keeps_cameras_frames_split_and_masks(source: Path, synth_capture: Path,
                                                     tmp_path: Path) -> None:
    assert detect_format(source) == "panoptic"
    cap = import_capture(source, tmp_path / "imported")
    ref = load_capture(synth_capture)
    assert list(cap.frames) == list(ref.frames)
    assert sorted(c.id for c in cap.cameras) == sorted(c.id for c in ref.cameras)
    for cam in ref.cameras:
        got = cap.camera(cam.id)
        np.testing.assert_allclose(got.K, cam.K, atol=1e-9)  # the half-pixel shift undone
        np.testing.assert_allclose(got.world_to_camera, cam.world_to_camera, atol=1e-9)
    assert cap.test_cameras == tuple(TEST_CAMERAS)
    assert cap.masks == "subject"
    # Masks come from seg/ for the training cameras only, as the dataset ships them.
    assert cap.mask_path(cap.frames[0], "cam01") is not None
    assert cap.mask_path(cap.frames[0], "cam00") is None
    assert validate_capture(tmp_path / "imported") == []
    saved = json.loads((tmp_path / "imported" / "capture.json").read_text())
    assert saved["test_cameras"] == TEST_CAMERAS and saved["masks"] == "subject"


def test_a_camera_that_moves_between_frames_is_refused_by_frame(source: Path,
                                                                tmp_path: Path) -> None:
    meta_path = source / "train_meta.json"
    meta = json.loads(meta_path.read_text())
    meta["w2c"][1][2][0][3] += 0.01  # frame 1, third training camera, moved by 1 cm
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(CaptureError) as err:
        import_capture(source, tmp_path / "imported")
    text = str(err.value)
    assert "frame 1" in text and "w2c differs from frame 0" in text and "one rig" in text
    assert not (tmp_path / "imported").exists()


def test_missing_keys_and_images_are_named(source: Path, tmp_path: Path) -> None:
    meta = json.loads((source / "test_meta.json").read_text())
    del meta["fn"]
    (source / "test_meta.json").write_text(json.dumps(meta))
    with pytest.raises(CaptureError, match="test_meta.json: fn: is missing"):
        import_capture(source, tmp_path / "a")
    (source / "test_meta.json").unlink()
    next((source / "ims").rglob("*.png")).unlink()
    with pytest.raises(CaptureError, match="not found"):
        import_capture(source, tmp_path / "b")


def test_split_rules(source: Path, tmp_path: Path, synth_capture: Path) -> None:
    cap = import_capture(source, tmp_path / "imported")
    ids = [c.id for c in cap.cameras]
    auto = camera_split(cap)
    assert auto.rule == "capture" and auto.heldout == tuple(TEST_CAMERAS)
    assert set(auto.training) == set(ids) - set(TEST_CAMERAS) and auto.scored == auto.heldout
    every8 = camera_split(cap, "every8")
    assert every8.heldout == (ids[0],) and not every8.on_training_views
    none = camera_split(cap, "none")
    assert none.heldout == () and none.training == tuple(ids)
    assert none.scored == tuple(ids) and none.to_json()["scored_on"] == "training views"
    plain = load_capture(synth_capture)  # declares no test cameras
    assert camera_split(plain).rule == "every8"
    with pytest.raises(ValueError, match="declares no test_cameras"):
        camera_split(plain, "capture")
    with pytest.raises(ValueError, match="split: expected one of"):
        camera_split(plain, "half")


def test_bad_test_cameras_fail_validation(capture_copy: Path) -> None:
    path = capture_copy / "capture.json"
    data = json.loads(path.read_text())
    data["test_cameras"] = ["cam00", "nope", "cam00"]
    path.write_text(json.dumps(data))
    messages = " ".join(p.message for p in validate_capture(capture_copy))
    assert "'nope' not among the cameras" in messages and "listed twice" in messages
    data["test_cameras"] = [c["id"] for c in data["cameras"]]
    data["masks"] = "alpha"
    path.write_text(json.dumps(data))
    messages = " ".join(p.message for p in validate_capture(capture_copy))
    assert "every camera is held out" in messages and "masks must be" in messages


TINY_RUN = ["--preset", "test", "--frames", "0:1", "--no-progress"]
TINY_CONFIG = {"train": {"schedule": {"iterations": 30, "stage2_start": 10, "stage3_start": 20,
                                      "densify_from": 2, "densify_until": 16,
                                      "densify_interval": 4, "reset_interval": 8,
                                      "sh_interval": 5}, "init_points": 200},
               "mesh": {"enabled": False}}


def test_a_run_trains_on_every_camera_and_says_so(synth_capture: Path, tmp_path: Path,
                                                   one_thread) -> None:
    from core.cli import main
    from core.evaluation import evaluate_run

    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps(TINY_CONFIG))
    run = tmp_path / "run"
    assert main(["reconstruct", str(synth_capture), "--out", str(run), "--split", "none",
                 "--method", "3dgs", "--config", str(cfg), *TINY_RUN]) == 0
    resolved = read_run(run)
    train = resolved.config.train
    assert resolved.config.split == "none" and train.method == "3dgs"
    assert resolved.views.split.rule == "none" and len(resolved.views.split.training) == 8
    # The method's defaults came under the file's settings, which still hold.
    assert train.densify.gradient == "mean"
    assert train.eps2d == 0.3 and train.init_points == 200
    renders = sorted(p.name for p in (run / "renders" / "000000").glob("*_rgb.png"))
    assert len(renders) == 8  # every camera trained, and is scored
    ev = evaluate_run(run)
    assert ev["split"] == {"rule": "none", "heldout": [], "scored_on": "training views",
                           "training_cameras": 8}
    assert ev["views"] == 8


def test_the_split_a_capture_cannot_follow_is_refused(synth_capture: Path,
                                                      tmp_path: Path) -> None:
    from core.cli import main

    code = main(["reconstruct", str(synth_capture), "--out", str(tmp_path / "run"),
                 "--split", "capture", *TINY_RUN])
    assert code == 2 and not (tmp_path / "run").exists()  # checked before anything is written
