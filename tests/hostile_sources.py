"""Issue 42's hostile capture files, for the importer tests (tests/core), the API tests (archive
and tus commit) and the live-server replay (tests/service/test_api_door_live.py): each one a
source exported from a real capture, then changed the way the review changed it. Every one
used to answer 500 retryable (a KeyError, TypeError, IndexError or AssertionError); each must
be refused naming the file and the field."""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

__all__ = ["ATTACKS", "Attack", "attacked", "source_files"]


@dataclass(frozen=True)
class Attack:
    name: str
    fmt: str
    """The importer (and the source exported for it)."""
    file: str
    """The metadata file changed, and named by the answer."""
    change: Callable[[dict, dict[str, bytes]], None]
    """Changes the decoded file (and, for renames, the other files of the source)."""
    field: str
    """The field the refusal names."""
    words: str
    """What the refusal says of it."""

    @property
    def message(self) -> str:
        """The start of the refusal's message (after the file)."""
        return f"{self.field}: {self.words}"


def _fn(value: str) -> Callable[[dict, dict[str, bytes]], None]:
    def change(meta: dict, files: dict[str, bytes]) -> None:
        meta["fn"][0][1] = value
    return change


def _cam_id_not_a_list(meta: dict, files: dict[str, bytes]) -> None:
    meta["cam_id"][0] = 3


def _empty(meta: dict, files: dict[str, bytes]) -> None:
    for key in ("k", "w2c", "fn", "cam_id"):
        meta[key] = [[] for _ in meta[key]]


def _renamed(old: str, new: str, folder: bool) -> Callable[[dict, dict[str, bytes]], None]:
    """A camera folder (or a frame's file name) renamed, in train_meta.json and in ims/."""
    def change(meta: dict, files: dict[str, bytes]) -> None:
        def rename(path: str) -> str:
            cam, _, name = path.rpartition("/")
            if folder:
                return path.replace(f"{old}/", f"{new}/", 1) if cam.endswith(old) else path
            return f"{cam}/{name.replace(old, new)}" if cam else path

        meta["fn"] = [[rename(fn) for fn in frame] for frame in meta["fn"]]
        for path in [p for p in files if p.startswith(("ims/", "seg/"))]:
            files[rename(path)] = files.pop(path)
    return change


def _intrinsics_as_text(meta: dict, files: dict[str, bytes]) -> None:
    meta["k"][0][0][0][0] = str(meta["k"][0][0][0][0])


def _camera_id(value: str) -> Callable[[dict, dict[str, bytes]], None]:
    def change(doc: dict, files: dict[str, bytes]) -> None:
        doc["frames"][0]["camera_id"] = value
    return change


ATTACKS: tuple[Attack, ...] = (
    Attack("fn leaves the source", "panoptic", "train_meta.json", _fn("../1/000000.png"),
           "fn[0][1]", "'../1/000000.png' has an empty, '.' or '..' component"),
    Attack("fn is absolute", "panoptic", "train_meta.json", _fn("/etc/000000.png"),
           "fn[0][1]", "'/etc/000000.png' is absolute"),
    Attack("cam_id[0] is a number", "panoptic", "train_meta.json", _cam_id_not_a_list,
           "cam_id[0]", "Input should be a valid array, got 3"),
    Attack("every frame's lists are empty", "panoptic", "train_meta.json", _empty,
           "k[0]", "List should have at least 1 item"),
    Attack("a camera folder outside ASCII", "panoptic", "train_meta.json",
           _renamed("cam01", "камера", folder=True), "fn[0][0]",
           "camera folder 'камера': character 0 ('к', U+043A) is outside ASCII"),
    Attack("a frame name outside ASCII", "panoptic", "train_meta.json",
           _renamed("000000", "кадр0", folder=False), "fn[0][0]",
           "frame 'кадр0': character 0 ('к', U+043A) is outside ASCII"),
    Attack("intrinsics as strings", "panoptic", "train_meta.json", _intrinsics_as_text,
           "k[0][0][0][0]", "Input should be a valid number, got '"),
    Attack("a Cyrillic camera id", "transforms", "transforms.json", _camera_id("камера0"),
           "frames[0].camera_id", "'камера0': character 0 ('к', U+043A) is outside ASCII"),
    Attack("a Roman-numeral camera id", "transforms", "transforms.json", _camera_id("Ⅻ0"),
           "frames[0].camera_id", "'Ⅻ0': character 0 ('Ⅻ', U+216B) is outside ASCII"),
)


def source_files(capture: Path, fmt: str) -> dict[str, bytes]:
    """The files of `capture` exported as a `fmt` source (panoptic: cam00 held out):
    relative path -> bytes."""
    from core.data import load_capture
    from core.data.importers.panoptic import export_panoptic
    from core.data.importers.transforms import export_transforms

    cap = load_capture(capture)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        if fmt == "panoptic":
            export_panoptic(cap, out, test_cameras=[cap.cameras[0].id])
        else:
            export_transforms(cap, out)
        return {p.relative_to(out).as_posix(): p.read_bytes()
                for p in sorted(out.rglob("*")) if p.is_file()}


def attacked(capture: Path, attack: Attack) -> dict[str, bytes]:
    """The source files of `capture` with `attack` applied."""
    files = source_files(capture, attack.fmt)
    doc = json.loads(files[attack.file])
    attack.change(doc, files)
    files[attack.file] = json.dumps(doc, ensure_ascii=False).encode()
    return files


def write(files: dict[str, bytes], root: Path) -> Path:
    """`files` written under `root`; returns `root`."""
    for rel, data in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    return root
