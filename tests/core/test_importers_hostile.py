"""Issue 42 at the importers: hostile files are refused with a CaptureError naming the file and
the field (never a KeyError, TypeError, IndexError or an assert), paths cannot leave the
source, names that cannot become ids are refused, numbers are numbers, and a metadata file's
size and count of values are bounded before it is parsed."""

from __future__ import annotations

import json
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from core.data import CaptureError, import_capture, load_capture, validate_capture
from core.data.importers.actorshq import export_actorshq
from core.data.importers.colmap import export_colmap
from core.data.importers.idr import export_idr
from core.data.importers.panoptic import PanopticMeta, export_panoptic
from core.data.importers.records import MAX_CAMERAS
from core.data.importers.transforms import export_transforms
from core.data.rules import MAX_JSON_VALUES, MAX_METADATA_BYTES, safe_name

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from hostile_sources import ATTACKS, attacked, write  # noqa: E402


def _refused(src: Path, out: Path, fmt: str = "auto") -> list[str]:
    """The problems, as 'file: message' with the file's name only; nothing written."""
    with pytest.raises(CaptureError) as err:
        import_capture(src, out, fmt)
    assert not out.exists()
    return [f"{Path(p.path).name}: {p.message}" for p in err.value.problems]


@pytest.mark.parametrize("attack", ATTACKS, ids=lambda a: a.name)
def test_each_finding_is_refused_naming_the_file_and_field(attack, synth_capture, tmp_path):
    src = write(attacked(synth_capture, attack), tmp_path / "src")
    problems = _refused(src, tmp_path / "out", attack.fmt)
    assert any(p.startswith(f"{attack.file}: {attack.message}") for p in problems), problems


def _panoptic(synth_capture: Path, dest: Path) -> Path:
    """The capture as a Panoptic source of one split (train_meta.json alone)."""
    export_panoptic(load_capture(synth_capture), dest, test_cameras=[])
    return dest


def test_a_huge_meta_file_is_refused_from_its_size(synth_capture, tmp_path, monkeypatch):
    """A train_meta.json past 64 MiB (a sparse file: nothing is written) is refused before a
    byte of it is read or parsed."""
    src = _panoptic(synth_capture, tmp_path / "src")
    with open(src / "train_meta.json", "r+b") as f:
        f.truncate(MAX_METADATA_BYTES + 1)
    monkeypatch.setattr(PanopticMeta, "model_validate_json", _never)
    problems = _refused(src, tmp_path / "out")
    assert problems == [f"train_meta.json: is {MAX_METADATA_BYTES + 1} bytes; a metadata file "
                        f"may have {MAX_METADATA_BYTES} (it is read whole, in memory)"]


def _never(*args, **kwargs):
    raise AssertionError("parsed, though it should have been refused before")


def test_the_frame_count_is_bounded_before_parsing(synth_capture, tmp_path, monkeypatch):
    """80,000 frames of one camera (12 MB, under the size limit) hold more JSON values than a
    metadata file may: refused from a count of its commas, before it is parsed."""
    src = _panoptic(synth_capture, tmp_path / "src")
    frames = 80_000
    K, E = json.dumps([[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]]), json.dumps([np.eye(4).tolist()])
    body = ('{"w": 48, "h": 48, "k": [' + ",".join([K] * frames) + '], "w2c": ['
            + ",".join([E] * frames) + '], "fn": [' + ",".join(['["cam01/000000.png"]'] * frames)
            + '], "cam_id": [' + ",".join(["[1]"] * frames) + "]}")
    (src / "train_meta.json").write_text(body)
    monkeypatch.setattr(PanopticMeta, "model_validate_json", _never)
    (problem,) = _refused(src, tmp_path / "out")
    assert problem.startswith("train_meta.json: holds about ") and \
        f"JSON values; a metadata file may hold {MAX_JSON_VALUES}" in problem


def test_the_camera_count_is_bounded(synth_capture, tmp_path):
    src = _panoptic(synth_capture, tmp_path / "src")
    meta = json.loads((src / "train_meta.json").read_text())
    for key in ("k", "w2c", "fn", "cam_id"):
        meta[key][0] = meta[key][0][:1] * (MAX_CAMERAS + 1)
    (src / "train_meta.json").write_text(json.dumps(meta))
    problems = _refused(src, tmp_path / "out")
    assert f"train_meta.json: k[0]: List should have at most {MAX_CAMERAS} items after " \
           f"validation, not {MAX_CAMERAS + 1}" in problems


def test_a_frame_whose_entries_name_two_frames_is_refused(synth_capture, tmp_path):
    src = _panoptic(synth_capture, tmp_path / "src")
    meta = json.loads((src / "train_meta.json").read_text())
    meta["fn"][1][2] = meta["fn"][0][2]  # frame 1 points at frame 0's image of one camera
    (src / "train_meta.json").write_text(json.dumps(meta))
    (problem,) = _refused(src, tmp_path / "out")
    assert problem.startswith("train_meta.json: fn[1][2]: 'cam02/000000.png' names another "
                              "frame than fn[1][0] ('000001')")


@pytest.mark.parametrize("key, value, words", [
    ("file_path", "../../outside.png", "frames[0].file_path: '../../outside.png' has an "
                                       "empty, '.' or '..' component"),
    ("file_path", "/etc/passwd.png", "frames[0].file_path: '/etc/passwd.png' is absolute"),
    ("mask_path", "..\\x.png", "frames[0].mask_path: '..\\\\x.png' contains a backslash"),
    ("fl_x", "500", "frames[0].fl_x: Input should be a valid number, got '500'"),
    ("camera_angle_x", 0, "frames[0].camera_angle_x: must be a field of view in (0, pi)"),
    ("transform_matrix", np.zeros((4, 4)).tolist(), "frames[0]: transform_matrix last row"),
])
def test_transforms_paths_stay_inside_and_numbers_are_numbers(synth_capture, tmp_path, key,
                                                              value, words):
    """A path out of the source used to be read (a file of another capture, on a server)."""
    export_transforms(load_capture(synth_capture), tmp_path / "src")
    path = tmp_path / "src" / "transforms.json"
    doc = json.loads(path.read_text())
    doc["frames"][0][key] = value
    if key == "camera_angle_x":  # else fl_x gives the focal length
        del doc["frames"][0]["fl_x"], doc["frames"][0]["fl_y"]
    path.write_text(json.dumps(doc))
    assert any(words in p for p in _refused(tmp_path / "src", tmp_path / "out"))


def test_colmap_names_and_tokens(synth_capture, tmp_path):
    model = export_colmap(load_capture(synth_capture), tmp_path / "src")
    lines = (model / "images.txt").read_text().splitlines()
    header = lines[1].split()
    lines[1] = " ".join(header[:9] + ["../../../outside.png"])
    lines[3] = lines[3].replace(lines[3].split()[1], "٣", 1)  # an Arabic-Indic digit as qw
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    problems = _refused(tmp_path / "src", tmp_path / "out")
    assert "images.txt: line 2: name: '../../../outside.png' has an empty, '.' or '..' " \
           "component" in problems
    assert "images.txt: line 4: qw: '٣' is not a number" in problems
    binary = export_colmap(load_capture(synth_capture), tmp_path / "bin", binary=True)
    data = bytearray((binary / "images.bin").read_bytes())
    struct.pack_into("<Q", data, 0, 2**63)  # the image count
    (binary / "images.bin").write_bytes(bytes(data))
    (problem,) = _refused(tmp_path / "bin", tmp_path / "out2")
    assert problem.startswith(f"images.bin: cannot parse COLMAP images: declares {2**63} images")


def test_actorshq_names_are_one_folder(synth_capture, tmp_path):
    csv = export_actorshq(load_capture(synth_capture), tmp_path / "src")
    rows = csv.read_text().splitlines()
    rows[1] = "../../x" + rows[1][rows[1].index(","):]
    rows[2] = "Kамера" + rows[2][rows[2].index(","):]
    csv.write_text("\n".join(rows) + "\n")
    problems = _refused(tmp_path / "src", tmp_path / "out")
    assert any(p.startswith("calibration.csv: row 2: name: '../../x' names a folder") and
               "one file name" for p in problems), problems
    assert any(p.startswith("calibration.csv: row 3: name: 'Kамера': character 1") for p in
               problems), problems


def test_idr_arrays_must_be_numbers_and_never_unpickled(synth_capture, tmp_path):
    npz = export_idr(load_capture(synth_capture), tmp_path / "src")
    arrays = dict(np.load(npz))
    arrays["world_mat_1"] = np.array(["x"] * 16).reshape(4, 4)
    np.savez(npz, **arrays)
    (problem,) = _refused(tmp_path / "src", tmp_path / "out")
    assert problem.startswith("cameras.npz: world_mat_1: must be an array of numbers")
    arrays["world_mat_1"] = np.array([{"a": 1}], dtype=object)  # would need a pickle
    np.savez(npz, **arrays)
    (problem,) = _refused(tmp_path / "src", tmp_path / "out2")
    assert problem.startswith("cameras.npz: cannot read as a .npz archive") and \
        "allow_pickle" in problem
    (tmp_path / "src" / "cameras.npz").write_bytes(npz.read_bytes()[:200])  # cut
    (problem,) = _refused(tmp_path / "src", tmp_path / "out3")
    assert problem.startswith("cameras.npz: cannot read as a .npz archive")


def test_a_long_id_in_capture_json_is_a_problem_not_an_os_error(capture_copy):
    path = capture_copy / "capture.json"
    data = json.loads(path.read_text())
    data["cameras"][0]["id"] = "c" * 300  # a file name longer than the file system allows
    data["frames"][0] = "f" * 300
    path.write_text(json.dumps(data))
    messages = [p.message for p in validate_capture(capture_copy)]
    assert any("id 'ccc" in m and "is not a safe file name" in m for m in messages)
    assert any("frame name 'fff" in m for m in messages)


@pytest.mark.parametrize("text, problem", [
    ("камера", "outside ASCII"), ("Ⅻ0", "outside ASCII"), ("a\x00", "not printable"),
    ("___", "no letter or digit"), ("", "is empty"), ("x" * 201, "characters long"),
])
def test_safe_name_refuses_instead_of_asserting(text, problem):
    with pytest.raises(ValueError, match=problem):
        safe_name(text)
    assert safe_name("./train/r 0.png") == "train_r_0.png"
