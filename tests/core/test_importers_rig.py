"""Issue 39 at the importers: a mirrored world is mirrored back once for the whole rig (cameras,
points, the way back to the source), a rig of mixed handedness is refused naming its cameras,
poses stored the other way round are refused naming the field and the fix while correct
few-camera and forward-facing rigs import as given, and an IDR folder with `images/` is read."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from core.cli import main
from core.data import CaptureError, import_capture, load_capture, save_capture, validate_capture
from core.data.capture import Camera, Capture
from core.data.images import write_png
from core.data.points import read_points_ply
from core.synth.generate import look_at

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from rig_sources import (  # noqa: E402
    MIRROR_Z,
    Y_DOWN,
    idr_files,
    inverted,
    mirrored,
    panoptic_files,
    points_npz,
    transforms_files,
    turned,
    write,
)

WRITERS = {"panoptic": panoptic_files, "transforms": transforms_files, "idr": idr_files}


def _project(cam: Camera, points: np.ndarray) -> np.ndarray:
    uv, z = cam.project(points)
    assert (z > 0).all()
    return uv


@pytest.mark.parametrize("fmt", sorted(WRITERS))
def test_a_mirrored_world_is_mirrored_back(fmt, synth_capture: Path, tmp_path: Path, capsys):
    ref = load_capture(synth_capture)
    files = WRITERS[fmt](mirrored(ref))
    world = np.random.default_rng(0).normal(0, 0.3, (40, 3)) + [0, 0, 0.9]  # near the subject
    source_points = world @ MIRROR_Z[:3, :3]  # the same points in the mirrored world
    if fmt == "panoptic":
        files["init_pt_cld.npz"] = points_npz(source_points)
    src = write(files, tmp_path / "src")
    assert main(["capture", "import", str(src), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "dgs: warning: " in err and "determinant -1" in err
    out = load_capture(tmp_path / "out")
    saved = json.loads((out.root / "capture.json").read_text())["import"]
    assert saved["warnings"] == out.import_record["warnings"]
    assert validate_capture(out.root) == []
    record = out.import_record
    assert record["mirrored_axis"] in ("x", "y", "z") and len(record["warnings"]) == 1
    assert "every camera's rotation has determinant -1" in record["warnings"][0]
    pairs = list(zip(ref.cameras, out.cameras)) if fmt == "idr" else \
        [(c, out.camera(c.id)) for c in ref.cameras]
    # One proper rotation takes the original rig to the imported one: the mirror undone.
    G = np.linalg.inv(pairs[0][0].world_to_camera) @ pairs[0][1].world_to_camera
    np.testing.assert_allclose(np.linalg.det(G[:3, :3]), 1.0, atol=1e-9)
    for a, b in pairs:
        np.testing.assert_allclose(np.linalg.det(b.R), 1.0, atol=1e-9)
        np.testing.assert_allclose(b.world_to_camera, a.world_to_camera @ G, atol=1e-6)
        np.testing.assert_allclose(b.K, a.K, atol=1e-6)
        frame = out.frames[0]
        assert out.image_path(frame, b.id).read_bytes() == \
            ref.image_path(ref.frames[0], a.id).read_bytes()
    # The import record leads back: source points through inv(source_from_world) land on the
    # pixels the original points do in the original cameras.
    S = np.asarray(record["to_source"]["source_from_world"])
    assert np.linalg.det(S[:3, :3]) < 0
    here = (np.linalg.inv(S) @ np.c_[source_points, np.ones(len(world))].T).T[:, :3]
    for a, b in pairs:
        np.testing.assert_allclose(_project(b, here), _project(a, world), atol=1e-5)
    if fmt == "panoptic":  # the points carry the same reflection as the cameras
        np.testing.assert_allclose(read_points_ply(out.root / "points.ply").points, here,
                                   atol=1e-5)
    if fmt == "transforms":  # a reflection that keeps the format's up
        assert record["mirrored_axis"] != "z" and out.up == (0.0, 0.0, 1.0)


def test_a_rig_of_mixed_handedness_is_refused_naming_cameras(synth_capture: Path,
                                                             tmp_path: Path) -> None:
    ref = load_capture(synth_capture)
    src = write(panoptic_files(mirrored(ref, {"cam02", "cam05"})), tmp_path / "src")
    with pytest.raises(CaptureError) as err:
        import_capture(src, tmp_path / "out")
    (problem,) = err.value.problems
    assert problem.path.endswith("train_meta.json")
    assert problem.message.startswith("w2c: the rotations of cameras cam02, cam05 have "
                                      "determinant -1 (a mirrored world) and those of cameras "
                                      "cam00, cam01, cam03, cam04, cam06, cam07 +1")
    assert not (tmp_path / "out").exists()


def test_camera_to_world_in_panoptic_w2c_is_refused(synth_capture: Path, tmp_path: Path):
    # Panoptic's own world is y-down; the synthetic rig is turned into one.
    files = panoptic_files(turned(load_capture(synth_capture), Y_DOWN))
    assert import_capture(write(files, tmp_path / "good"), tmp_path / "good_out")
    with pytest.raises(CaptureError) as err:
        import_capture(write(inverted(files), tmp_path / "src"), tmp_path / "out")
    (problem,) = err.value.problems
    assert problem.path.endswith("train_meta.json")
    assert problem.message.startswith("w2c: these look like camera-to-world poses, but this "
                                      "field holds world-to-camera ones: as given, the cameras "
                                      "look away from each other")
    assert "Invert each matrix, or give the poses in a format that holds camera-to-world" in \
        problem.message
    assert not (tmp_path / "out").exists()


def test_world_to_camera_in_transform_matrix_is_refused(synth_capture: Path, tmp_path: Path):
    files = inverted(transforms_files(load_capture(synth_capture)))
    with pytest.raises(CaptureError) as err:
        import_capture(write(files, tmp_path / "src"), tmp_path / "out")
    (problem,) = err.value.problems
    assert problem.path.endswith("transforms.json")
    assert problem.message.startswith("frames[*].transform_matrix: these look like "
                                      "world-to-camera poses, but this field holds "
                                      "camera-to-world ones")
    assert "Invert each matrix" in problem.message


def _forward_facing(root: Path, n: int = 9) -> Capture:
    """A forward-facing rig (a 3x3 grid 20 cm apart aimed at a point 3 m ahead), y down."""
    K = np.array([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]])
    cams = []
    for i in range(n):
        eye = np.array([(i % 3) - 1, (i // 3) - 1, 0.0]) * 0.2
        cams.append(Camera(f"cam{i:02d}", 16, 16, K, look_at(eye, [0, 0, 3.0], [0, -1, 0])))
        write_png(root / "images" / "000000" / f"cam{i:02d}.png", np.zeros((16, 16, 3), np.uint8))
    capture = Capture(root, tuple(cams), ("000000",), (0.0, -1.0, 0.0))
    save_capture(capture)
    return capture


@pytest.mark.parametrize("fmt", ["panoptic", "transforms"])
def test_correct_rigs_import_and_weak_evidence_is_not_a_guess(fmt, synth_capture: Path,
                                                              tmp_path: Path) -> None:
    """Few cameras and a forward-facing rig import as given; so do the same poses inverted,
    where the other reading is no better (a forward-facing rig inverted is one too) or the rig
    has too few cameras to say: the rule refuses only on strong evidence."""
    ref = load_capture(synth_capture)
    few = type(ref)(ref.root, ref.cameras[:3], ref.frames, ref.up)  # the rule needs 4
    forward = _forward_facing(tmp_path / "forward")
    for name, capture in (("few", few), ("forward", forward)):
        files = WRITERS[fmt](capture)
        for how, these in (("as given", files), ("inverted", inverted(files))):
            out = import_capture(write(these, tmp_path / name / how),
                                 tmp_path / name / f"{how}-out")
            assert len(out.cameras) == len(capture.cameras), (name, how)
            assert "warnings" not in out.import_record
    good = import_capture(write(WRITERS[fmt](forward), tmp_path / "f"), tmp_path / "f-out")
    for cam in forward.cameras:
        np.testing.assert_allclose(good.camera(cam.id).world_to_camera, cam.world_to_camera,
                                   atol=1e-9)


def test_idr_images_and_masks_folders(synth_capture: Path, tmp_path: Path) -> None:
    ref = load_capture(synth_capture)
    singular = import_capture(write(idr_files(ref), tmp_path / "a"), tmp_path / "a-out")
    files = idr_files(ref, plural=True)
    assert any(k.startswith("images/") for k in files) and not any(
        k.startswith("image/") for k in files)
    plural = import_capture(write(files, tmp_path / "b"), tmp_path / "b-out")
    assert validate_capture(plural.root) == []
    assert [c.id for c in plural.cameras] == [c.id for c in singular.cameras]
    for a, b in zip(singular.cameras, plural.cameras):
        np.testing.assert_array_equal(a.world_to_camera, b.world_to_camera)
        assert plural.mask_path("000000", b.id) is not None
    both = write(idr_files(ref), tmp_path / "b")  # image/ beside images/: which is it?
    with pytest.raises(CaptureError, match="both image/ and images/ hold images"):
        import_capture(both, tmp_path / "c-out")


def test_a_colmap_model_is_the_solvers_and_never_refused_for_direction(synth_capture: Path,
                                                                        tmp_path: Path) -> None:
    """COLMAP writes the poses it solved in its one convention: the rig whose Panoptic `w2c` is
    refused above (cameras looking away from each other, as in a room scanned from its middle)
    imports from a COLMAP model as given."""
    import dataclasses

    from core.data.importers.colmap import export_colmap

    ref = turned(load_capture(synth_capture), Y_DOWN)
    outward = dataclasses.replace(ref, cameras=tuple(
        dataclasses.replace(c, world_to_camera=np.linalg.inv(c.world_to_camera))
        for c in ref.cameras))
    with pytest.raises(CaptureError):  # the same poses as a hand-written w2c field
        import_capture(write(panoptic_files(outward), tmp_path / "p"), tmp_path / "p-out")
    export_colmap(outward, tmp_path / "src")
    out = import_capture(tmp_path / "src", tmp_path / "out")
    for cam in outward.cameras:
        np.testing.assert_allclose(out.camera(cam.id).world_to_camera, cam.world_to_camera,
                                   atol=1e-6)
