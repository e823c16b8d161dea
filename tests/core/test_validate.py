"""Validation: every kind of bad input is reported, naming the file and the problem, in one pass."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from core.cli import main
from core.data import CaptureError, Problem, check_capture, validate_capture


def _edit_json(root: Path, fn) -> None:
    path = root / "capture.json"
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def _messages(problems: list[Problem]) -> list[str]:
    return [f"{p.path}: {p.message}" for p in problems]


def _only(problems: list[Problem], needle: str, path_part: str) -> Problem:
    hits = [p for p in problems if needle in p.message and path_part in p.path]
    assert hits, f"no problem with {needle!r} at {path_part!r} in {_messages(problems)}"
    return hits[0]


def test_synthetic_capture_is_valid(synth_capture: Path) -> None:
    assert validate_capture(synth_capture) == []
    capture = check_capture(synth_capture)
    assert len(capture.cameras) == 8 and capture.frames == ("000000", "000001")


def test_missing_image(capture_copy: Path) -> None:
    (capture_copy / "images/000001/cam03.png").unlink()
    _only(validate_capture(capture_copy), "missing image", "images/000001/cam03")


def test_unreadable_images(capture_copy: Path) -> None:
    (capture_copy / "images/000000/cam01.png").write_bytes(b"not a png at all")
    data = (capture_copy / "images/000000/cam02.png").read_bytes()
    (capture_copy / "images/000000/cam02.png").write_bytes(data[: len(data) // 2])  # truncated
    problems = validate_capture(capture_copy)
    _only(problems, "not a PNG file", "images/000000/cam01.png")
    _only(problems, "cannot decode", "images/000000/cam02.png")


def test_size_disagrees_with_camera(capture_copy: Path) -> None:
    _edit_json(capture_copy, lambda d: d["cameras"][2].update(width=50))
    problem = _only(
        validate_capture(capture_copy), "disagrees with camera", "images/000000/cam02.png"
    )
    assert "48x48" in problem.message and "50x48" in problem.message


@pytest.mark.parametrize(
    "K, needle",
    [
        ([[float("nan"), 0, 24], [0, 60, 24], [0, 0, 1]], "non-finite"),
        ([[float("inf"), 0, 24], [0, 60, 24], [0, 0, 1]], "non-finite"),
        ([[0.0, 0, 24], [0, 60, 24], [0, 0, 1]], "degenerate focal"),
        ([[-60.0, 0, 24], [0, 60, 24], [0, 0, 1]], "degenerate focal"),
        ([[60.0, 0, 24], [0, 60, 24], [0, 0, 2]], "must have the form"),
        ([[60.0, 0], [0, 60]], "3x3"),
    ],
)
def test_bad_intrinsics(capture_copy: Path, K, needle: str) -> None:
    _edit_json(capture_copy, lambda d: d["cameras"][4].update(K=K))
    problem = _only(validate_capture(capture_copy), needle, "capture.json")
    assert "cam04" in problem.message


@pytest.mark.parametrize("kind", ["scaled", "reflection", "shear", "last_row"])
def test_rotation_that_is_not_a_rotation(capture_copy: Path, kind: str) -> None:
    def edit(d):
        m = np.array(d["cameras"][5]["world_to_camera"])
        if kind == "scaled":
            m[:3, :3] *= 1.1
        elif kind == "reflection":
            m[:3, 0] *= -1
        elif kind == "shear":
            m[0, 1] += 0.2
        else:
            m[3, 0] = 0.5
        d["cameras"][5]["world_to_camera"] = m.tolist()

    _edit_json(capture_copy, edit)
    problem = _only(validate_capture(capture_copy), "world_to_camera", "capture.json")
    assert "cam05" in problem.message


def test_duplicate_ids(capture_copy: Path) -> None:
    def edit(d):
        d["cameras"][1]["id"] = "cam00"
        d["frames"].append("000000")

    _edit_json(capture_copy, edit)
    messages = [p.message for p in validate_capture(capture_copy)]
    assert any("duplicate camera id 'cam00'" in m for m in messages), messages
    assert any("duplicate frame '000000'" in m for m in messages), messages


def test_mask_of_wrong_size(capture_copy: Path) -> None:
    from core.data.images import write_png

    write_png(capture_copy / "masks/000001/cam06.png", np.zeros((40, 48), np.uint8))
    problem = _only(
        validate_capture(capture_copy), "disagrees with camera", "masks/000001/cam06.png"
    )
    assert "48x40" in problem.message


def test_unsupported_file_types(capture_copy: Path) -> None:
    os.rename(capture_copy / "images/000000/cam07.png", capture_copy / "images/000000/cam07.bmp")
    (capture_copy / "masks/000000/cam01.jpg").write_bytes(b"x")
    problems = validate_capture(capture_copy)
    _only(problems, "unsupported file type '.bmp'", "images/000000/cam07.bmp")
    _only(problems, "missing image", "images/000000/cam07")
    _only(problems, "unsupported file type '.jpg'", "masks/000000/cam01.jpg")


def test_symlinks_and_escapes(capture_copy: Path, tmp_path: Path) -> None:
    outside = tmp_path / "outside.png"
    shutil.copyfile(capture_copy / "images/000000/cam00.png", outside)
    (capture_copy / "images/000000/cam00.png").unlink()
    os.symlink(outside, capture_copy / "images/000000/cam00.png")
    (capture_copy / "images/000001/cam00.png").unlink()
    os.symlink("cam01.png", capture_copy / "images/000001/cam00.png")  # stays inside, still refused
    problems = validate_capture(capture_copy)
    _only(problems, "points outside the capture folder", "images/000000/cam00.png")
    _only(problems, "is a symlink", "images/000001/cam00.png")


def test_symlinked_folder_is_refused(capture_copy: Path, tmp_path: Path) -> None:
    shutil.move(capture_copy / "masks", tmp_path / "masks")
    os.symlink(tmp_path / "masks", capture_copy / "masks")
    _only(validate_capture(capture_copy), "symlink", "masks")


def test_ids_that_would_leave_the_folder(capture_copy: Path) -> None:
    _edit_json(capture_copy, lambda d: d["cameras"][0].update(id="../../etc/passwd"))
    _only(validate_capture(capture_copy), "not a safe file name", "capture.json")


def test_unknown_camera_and_frame_files(capture_copy: Path) -> None:
    shutil.copyfile(
        capture_copy / "images/000000/cam00.png", capture_copy / "images/000000/cam99.png"
    )
    (capture_copy / "images/000009").mkdir()
    problems = validate_capture(capture_copy)
    _only(problems, "capture.json does not list", "images/000000/cam99.png")
    _only(problems, "capture.json does not list", "images/000009")


def test_bad_capture_json(capture_copy: Path) -> None:
    (capture_copy / "capture.json").write_text("{not json")
    _only(validate_capture(capture_copy), "cannot parse", "capture.json")
    (capture_copy / "capture.json").unlink()
    _only(validate_capture(capture_copy), "not found", "capture.json")


def test_all_problems_in_one_pass_and_nothing_written(capture_copy: Path, digest) -> None:
    (capture_copy / "images/000001/cam03.png").unlink()
    (capture_copy / "images/000000/cam01.png").write_bytes(b"garbage")
    _edit_json(capture_copy, lambda d: d["cameras"][4]["K"][0].__setitem__(0, 0.0))
    before = digest(capture_copy)
    problems = validate_capture(capture_copy)
    assert digest(capture_copy) == before
    assert len(problems) >= 3, _messages(problems)
    with pytest.raises(CaptureError) as err:
        check_capture(capture_copy)
    text = str(err.value)
    assert "cam03" in text and "cam01.png" in text and "degenerate focal" in text


def test_cli_validate_exit_codes(synth_capture: Path, capture_copy: Path, capsys) -> None:
    assert main(["capture", "validate", str(synth_capture)]) == 0
    assert "valid" in capsys.readouterr().out
    (capture_copy / "images/000001/cam02.png").write_bytes(b"broken")
    assert main(["capture", "validate", str(capture_copy)]) != 0
    err = capsys.readouterr().err
    assert str(capture_copy / "images/000001/cam02.png") in err and "not a PNG file" in err


def test_not_a_capture_folder(tmp_path: Path, capsys) -> None:
    assert main(["capture", "validate", str(tmp_path / "nope")]) == 1
    assert str(tmp_path / "nope") in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    problems = validate_capture(tmp_path / "empty")
    assert problems and "capture.json not found" in problems[0].message


def test_validation_and_import_do_not_load_torch() -> None:
    """The API process validates uploads and must stay torch-free (docs/design.md section 2)."""
    import subprocess
    import sys

    code = (
        "import sys, core.data, core.data.validate, core.data.importers.transforms, "
        "core.data.importers.colmap, core.data.importers.actorshq; "
        "assert 'torch' not in sys.modules, 'torch imported'"
    )
    root = Path(__file__).resolve().parents[2]
    subprocess.run([sys.executable, "-c", code], check=True, cwd=root)


def test_unsafe_frame_names_are_not_followed(capture_copy: Path) -> None:
    _edit_json(capture_copy, lambda d: d["frames"].append("../../.."))
    problems = validate_capture(capture_copy)
    _only(problems, "not a safe file name", "capture.json")
    assert all("../" not in p.path for p in problems)
