"""Importers: round trips through every format, source conventions, errors, and no side effects."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from core.cli import main
from core.data import CaptureError, detect_format, import_capture, load_capture, validate_capture
from core.data.images import write_png
from core.data.importers.actorshq import export_actorshq
from core.data.importers.colmap import export_colmap
from core.data.importers.transforms import export_transforms

TOL = 1e-6
# A real capture to import, when one is at hand (the instant-ngp fox: 67 views, 1080x1920).
FOX = Path(os.environ.get("DGS_TEST_FOX", "/nonexistent"))


def assert_same_cameras(a, b) -> None:
    ids_a = sorted(c.id for c in a.cameras)
    assert ids_a == sorted(c.id for c in b.cameras)
    for cam in a.cameras:
        other = b.camera(cam.id)
        assert (cam.width, cam.height) == (other.width, other.height)
        np.testing.assert_allclose(cam.K, other.K, atol=TOL, rtol=0)
        np.testing.assert_allclose(cam.world_to_camera, other.world_to_camera, atol=TOL, rtol=0)
        np.testing.assert_allclose(
            cam.distortion or (0,) * 5, other.distortion or (0,) * 5, atol=TOL
        )


def _with_distortion(capture_copy: Path) -> Path:
    path = capture_copy / "capture.json"
    data = json.loads(path.read_text())
    data["cameras"][1]["distortion"] = [0.05, -0.02, 0.001, -0.0005, 0.0]
    data["cameras"][2]["distortion"] = [0.03, 0.01, 0.0, 0.0, -0.004]
    path.write_text(json.dumps(data))
    return capture_copy


@pytest.mark.parametrize("fmt", ["transforms", "colmap-text", "colmap-binary", "actorshq"])
def test_round_trip(fmt: str, capture_copy: Path, tmp_path: Path, digest) -> None:
    if fmt != "actorshq":
        _with_distortion(capture_copy)
    source = load_capture(capture_copy)
    src = tmp_path / "exported"
    if fmt == "transforms":
        export_transforms(source, src)
    elif fmt.startswith("colmap"):
        export_colmap(source, src, binary=fmt.endswith("binary"))
    else:
        export_actorshq(source, src)
    expected = fmt.split("-")[0]
    assert detect_format(src) == expected
    before = digest(src)
    out = import_capture(src, tmp_path / "imported")
    assert digest(src) == before, "import modified its source"
    assert validate_capture(out.root) == []
    assert out.import_record["format"] == expected
    assert_same_cameras(source, out)
    assert len(out.frames) == len(source.frames) == 2
    for i, frame in enumerate(source.frames):  # same pixels land in the same view
        for cam in source.cameras[:3]:
            a = source.image_path(frame, cam.id).read_bytes()
            assert out.image_path(out.frames[i], cam.id).read_bytes() == a
    assert any((out.root / "source").iterdir()), "source metadata not kept"


def test_single_frame_colmap_and_transforms(synth_capture: Path, tmp_path: Path) -> None:
    source = load_capture(synth_capture)
    one = type(source)(source.root, source.cameras, source.frames[:1], source.up)
    export_colmap(one, tmp_path / "colmap")
    export_transforms(one, tmp_path / "tf")
    for name in ("colmap", "tf"):
        out = import_capture(tmp_path / name, tmp_path / f"{name}_out")
        assert out.frames == ("000000",)
        assert_same_cameras(one, out)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_transforms_reprojection_follows_opengl_convention(tmp_path: Path) -> None:
    """A point projected with the source's own convention lands on the same pixel after import."""
    rng = np.random.default_rng(7)
    w, h, fx, fy, cx, cy = 40, 30, 35.0, 36.5, 19.2, 15.7
    frames, points = [], rng.normal(scale=0.3, size=(20, 3))
    for i in range(4):
        c2w = np.eye(4)
        c2w[:3, :3] = _random_rotation(rng)
        c2w[:3, 3] = c2w[:3, :3] @ np.array([0, 0, 4.0])  # camera looks down its -z at the origin
        write_png(tmp_path / "src" / f"v{i}.png", np.zeros((h, w, 3), np.uint8))
        frames.append({"file_path": f"v{i}.png", "transform_matrix": c2w.tolist()})
    doc = {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": w, "h": h, "frames": frames}
    (tmp_path / "src" / "transforms.json").write_text(json.dumps(doc))
    cap = import_capture(tmp_path / "src", tmp_path / "out")
    back = cap.import_record["to_source"]
    for entry in frames:  # the record leads back to the source's own matrices
        w2c = cap.camera(Path(entry["file_path"]).stem).world_to_camera
        c2w = (
            np.array(back["source_from_world"])
            @ np.linalg.inv(w2c)
            @ np.array(back["source_camera_from_camera"])
        )
        np.testing.assert_allclose(c2w, entry["transform_matrix"], atol=1e-12)
    for entry in frames:
        c2w = np.array(entry["transform_matrix"])
        local = (np.linalg.inv(c2w) @ np.c_[points, np.ones(len(points))].T).T[:, :3]
        # OpenGL: x right, y up, camera looks down -z; image v grows downwards.
        u = cx + fx * local[:, 0] / -local[:, 2]
        v = cy - fy * local[:, 1] / -local[:, 2]
        uv, z = cap.camera(Path(entry["file_path"]).stem).project(points)
        np.testing.assert_allclose(uv, np.stack([u, v], 1), atol=1e-9)
        np.testing.assert_allclose(z, -local[:, 2], atol=1e-9)


def test_distortion_matches_opencv() -> None:
    import cv2

    from core.data import Camera

    rng = np.random.default_rng(1)
    w2c = np.eye(4)
    w2c[:3, :3] = _random_rotation(rng)
    w2c[:3, 3] = [0.1, -0.2, 3.0]
    K = np.array([[50.0, 0, 31.0], [0, 52.0, 29.0], [0, 0, 1]])
    dist = (0.05, -0.02, 0.001, -0.0005, 0.003)
    cam = Camera("c", 64, 60, K, w2c, dist)
    pts = rng.normal(scale=0.5, size=(30, 3))
    ref, _ = cv2.projectPoints(pts, cv2.Rodrigues(w2c[:3, :3])[0], w2c[:3, 3], K, np.array(dist))
    np.testing.assert_allclose(cam.project(pts)[0], ref[:, 0], atol=1e-9)


def test_nerf_synthetic_splits_with_camera_angle(tmp_path: Path) -> None:
    """transforms_{train,test}.json, camera_angle_x only, extension-less RGBA file paths."""
    src = tmp_path / "lego"
    rgba = np.zeros((20, 24, 4), np.uint8)
    rgba[5:15, 6:18] = [200, 100, 50, 255]
    for split in ("train", "test"):
        frames = []
        for i in range(2):
            write_png(src / split / f"r_{i}.png", rgba)
            c2w = np.eye(4)
            c2w[:3, 3] = [0, 0, 3.0 + i]
            frames.append(
                {"file_path": f"./{split}/r_{i}", "rotation": 0.1, "transform_matrix": c2w.tolist()}
            )
        doc = {"camera_angle_x": 0.69, "frames": frames}
        (src / f"transforms_{split}.json").write_text(json.dumps(doc))
    cap = import_capture(src, tmp_path / "out")
    assert sorted(c.id for c in cap.cameras) == ["test_r_0", "test_r_1", "train_r_0", "train_r_1"]
    cam = cap.camera("train_r_1")
    assert (cam.width, cam.height) == (24, 20)
    assert (
        cam.K[0, 0] == pytest.approx(12.0 / math.tan(0.345), abs=TOL) and cam.K[1, 1] == cam.K[0, 0]
    )
    assert (cam.K[0, 2], cam.K[1, 2]) == (12.0, 10.0)
    np.testing.assert_allclose(cam.center, [0, 0, 4.0], atol=TOL)
    assert cap.import_record["views"]["000000/train_r_0"]["rotation"] == 0.1  # nothing lost
    from core.data import CaptureDataset

    sample = CaptureDataset(cap)[cap.cameras.index(cam)]
    assert sample.mask is not None and sample.mask[10, 10, 0] == 1.0 and sample.mask[0, 0, 0] == 0.0


def test_transforms_errors_name_file_and_problem(tmp_path: Path, digest) -> None:
    src = tmp_path / "src"
    write_png(src / "a.png", np.zeros((10, 10, 3), np.uint8))
    bad_rot = np.eye(4)
    bad_rot[:3, :3] *= 2
    frames = [
        {"file_path": "a.png", "transform_matrix": np.eye(4).tolist()},
        {"file_path": "missing.png", "transform_matrix": np.eye(4).tolist()},
        {"file_path": "a.png", "transform_matrix": bad_rot.tolist(), "camera_id": "b"},
        {
            "file_path": "a.png",
            "transform_matrix": np.eye(4).tolist(),
            "camera_id": "c",
            "fl_x": float("nan"),
        },
    ]
    (src / "transforms.json").write_text(json.dumps({"fl_x": 10, "frames": frames}))
    before = digest(src)
    with pytest.raises(CaptureError) as err:
        import_capture(src, tmp_path / "out")
    text = str(err.value)
    assert (
        "missing.png" in text
        and "not a rotation" in text
        and "frames[2]" in text
        and "frames[3].fl_x: Input should be a finite number" in text
    )
    assert not (tmp_path / "out").exists() and digest(src) == before


def test_transforms_unsupported_camera_model(tmp_path: Path) -> None:
    src = tmp_path / "src"
    write_png(src / "a.png", np.zeros((10, 10, 3), np.uint8))
    doc = {
        "camera_model": "OPENCV_FISHEYE",
        "fl_x": 10,
        "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}],
    }
    (src / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match="OPENCV_FISHEYE"):
        import_capture(src, tmp_path / "out")


def test_import_into_existing_folder_is_refused(synth_capture: Path, tmp_path: Path) -> None:
    export_transforms(load_capture(synth_capture), tmp_path / "src")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    with pytest.raises(CaptureError, match="not an empty folder"):
        import_capture(tmp_path / "src", tmp_path / "out")
    assert (tmp_path / "out" / "keep.txt").read_text() == "mine"


def test_colmap_models_and_errors(tmp_path: Path) -> None:
    src = tmp_path / "colmap"
    model = src / "sparse" / "0"
    model.mkdir(parents=True)
    write_png(src / "images" / "a.png", np.zeros((30, 40, 3), np.uint8))
    write_png(src / "images" / "b.png", np.zeros((30, 40, 3), np.uint8))
    (model / "cameras.txt").write_text(
        "# c\n1 SIMPLE_RADIAL 40 30 33.0 20.5 14.5 0.02\n2 OPENCV_FISHEYE 40 30 1 1 1 1 0 0 0 0\n"
    )
    (model / "images.txt").write_text(
        "# i\n1 1 0 0 0 0.5 0 2 1 a.png\n1 2 -1\n2 1 0 0 0 0 0 2 2 b.png\n\n"
    )
    with pytest.raises(CaptureError) as err:
        import_capture(src, tmp_path / "out")
    assert "cameras.txt" in str(err.value) and "OPENCV_FISHEYE" in str(err.value)
    (model / "images.txt").write_text(
        "# i\n1 0.7071067811865476 0.7071067811865476 0 0 0.5 0 2 1 a.png\n1 2 -1\n"
    )
    cap = import_capture(src, tmp_path / "out")
    cam = cap.camera("a")
    np.testing.assert_allclose(cam.K, [[33.0, 0, 20.5], [0, 33.0, 14.5], [0, 0, 1]])
    assert cam.distortion == (0.02, 0.0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(cam.R, [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)
    np.testing.assert_allclose(cam.t, [0.5, 0, 2], atol=1e-12)


def test_colmap_binary_truncated(synth_capture: Path, tmp_path: Path) -> None:
    model = export_colmap(load_capture(synth_capture), tmp_path / "src", binary=True)
    data = (model / "images.bin").read_bytes()
    (model / "images.bin").write_bytes(data[:100])
    with pytest.raises(CaptureError, match="images.bin"):
        import_capture(tmp_path / "src", tmp_path / "out")


def test_actorshq_convention_and_errors(tmp_path: Path) -> None:
    src = tmp_path / "ahq"
    rvec = np.array([0.1, -0.4, 0.25])
    row = "Cam001,40,30," + ",".join(map(str, [*rvec, 1.0, 2.0, 3.0, 0.9, 1.2, 0.5, 0.45]))
    (src / "rgbs" / "Cam001").mkdir(parents=True)
    (src / "calibration.csv").write_text("name,w,h,rx,ry,rz,tx,ty,tz,fx,fy,px,py\n" + row + "\n")
    for f in (0, 1):
        write_png(
            src / "rgbs" / "Cam001" / f"Cam001_rgb{f:06d}.jpg".replace(".jpg", ".png"),
            np.zeros((30, 40, 3), np.uint8),
        )
    cap = import_capture(src, tmp_path / "out", "actorshq")
    cam = cap.camera("Cam001")
    import cv2

    np.testing.assert_allclose(cam.center, [1, 2, 3], atol=TOL)
    np.testing.assert_allclose(cam.R.T, cv2.Rodrigues(rvec)[0], atol=TOL)
    np.testing.assert_allclose(cam.K, [[36, 0, 20], [0, 36, 13.5], [0, 0, 1]], atol=TOL)
    assert cap.frames == ("000000", "000001")
    (src / "calibration.csv").write_text(
        "name,w,h,rx,ry,rz,tx,ty,tz,fx,fy,px,py\n" + row + "\n" + row.replace("0.9", "nan") + "\n"
    )
    with pytest.raises(CaptureError) as err:
        import_capture(src, tmp_path / "out2", "actorshq")
    assert "calibration.csv" in str(err.value) and (
        "duplicate" in str(err.value)
        or "row 3: fx: Input should be a finite number" in str(err.value)
    )


def test_cli_import_and_failure(synth_capture: Path, tmp_path: Path, capsys) -> None:
    export_colmap(load_capture(synth_capture), tmp_path / "src")
    assert main(["capture", "import", str(tmp_path / "src"), "--out", str(tmp_path / "out")]) == 0
    assert main(["capture", "validate", str(tmp_path / "out")]) == 0
    os.remove(tmp_path / "src" / "images" / "000001" / "cam02.png")
    assert main(["capture", "import", str(tmp_path / "src"), "--out", str(tmp_path / "out2")]) == 1
    err = capsys.readouterr().err
    assert str(tmp_path / "src" / "images" / "000001" / "cam02.png") in err and "not found" in err


@pytest.mark.skipif(not FOX.is_dir(), reason="set DGS_TEST_FOX to the instant-ngp fox folder")
def test_real_fox_capture(tmp_path: Path) -> None:
    cap = import_capture(FOX, tmp_path / "fox")
    assert len(cap.cameras) == 67 and validate_capture(cap.root) == []
    cam = cap.cameras[0]
    assert cam.distortion is not None and (cam.width, cam.height) == (1080, 1920)
    # The point nearest to all optical axes (the fox) must be in front of and inside every view:
    # with the OpenGL->OpenCV flip wrong, cameras would face away from it.
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in cap.cameras:
        d = c.R[2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    target = np.linalg.solve(A, b)
    for c in cap.cameras:
        uv, z = c.project(target[None])
        assert z[0] > 0 and 0 <= uv[0, 0] < c.width and 0 <= uv[0, 1] < c.height


def test_colmap_rig_folders_stay_one_frame(tmp_path: Path) -> None:
    """``<camera>/<shot>.png`` names with differing poses are not misread as frames."""
    src = tmp_path / "rig"
    model = src / "sparse" / "0"
    model.mkdir(parents=True)
    lines = []
    for i, name in enumerate(
        ["left/0001.png", "left/0002.png", "right/0001.png", "right/0002.png"]
    ):
        write_png(src / "images" / name, np.zeros((30, 40, 3), np.uint8))
        lines += [f"{i + 1} 1 0 0 0 {0.1 * i} 0 2 1 {name}", ""]
    (model / "cameras.txt").write_text("1 PINHOLE 40 30 30 30 20 15\n")
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    cap = import_capture(src, tmp_path / "out")
    assert cap.frames == ("000000",)
    assert sorted(c.id for c in cap.cameras) == [
        "left_0001",
        "left_0002",
        "right_0001",
        "right_0002",
    ]
    np.testing.assert_allclose(cap.camera("right_0002").t, [0.3, 0, 2])


def test_transforms_multi_frame_consistency(synth_capture: Path, tmp_path: Path) -> None:
    export_transforms(load_capture(synth_capture), tmp_path / "src")
    path = tmp_path / "src" / "transforms.json"
    doc = json.loads(path.read_text())
    moved = next(e for e in doc["frames"] if e["time"] == 1 and e["camera_id"] == "cam04")
    moved["transform_matrix"][0][3] += 0.5
    dup = next(e for e in doc["frames"] if e["time"] == 0 and e["camera_id"] == "cam01")
    doc["frames"].append(dict(dup))
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError) as err:
        import_capture(tmp_path / "src", tmp_path / "out")
    messages = [f"{p.path}: {p.message}" for p in err.value.problems]
    assert any(str(path) in m and "'cam04' changes pose" in m for m in messages), messages
    assert any(str(path) in m and "duplicate camera id 'cam01'" in m for m in messages), messages
