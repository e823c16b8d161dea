"""Typed records of the importers' source files: each file is read under its limits and parsed
into strict pydantic models before a reader uses a value of it, so a reader works on names that
can become ids, paths that stay inside the source, numbers that are numbers and lists whose
lengths are bounded, and every problem names the file and the field (``fn[0][3]: ...``).

The rules themselves (names, paths, sizes) are `core.data.rules`; the counts are below.
"""

from __future__ import annotations

import zipfile
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, TypeVar

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PlainValidator,
    TypeAdapter,
    ValidationError,
)
from pydantic_core import PydanticCustomError

from core.data.capture import CaptureError, Problem
from core.data.rules import (
    MAX_METADATA_BYTES,
    json_values_problem,
    name_problem,
    path_problem,
    read_bounded,
)

__all__ = [
    "FieldError",
    "IdOrNumber",
    "MAX_ARRAY_BYTES",
    "MAX_CAMERAS",
    "MAX_FRAMES",
    "MAX_SIDE",
    "MAX_VIEWS",
    "Number",
    "Record",
    "Side",
    "SourceName",
    "SourcePath",
    "checked",
    "field_problems",
    "listof",
    "load_json",
    "load_npz",
    "matrix",
    "read_text",
    "stem",
    "where",
]

MAX_FRAMES = 100_000
"""Most frames a source may declare (an hour at 30 fps is 108,000: split it)."""
MAX_CAMERAS = 10_000
"""Most cameras a source may declare (studio rigs have tens to a few hundred)."""
MAX_VIEWS = 1_000_000
"""Most views (entries, images) a source may list: a capture holds at most a million files by
default (the service's `max_capture_files`)."""
MAX_SIDE = 1 << 16
"""Largest image width or height a source may declare, in pixels."""
MAX_ARRAY_BYTES = 1 << 30
"""Largest array a source's .npz may hold once decompressed (its header says so before any is
loaded): 38M points of Panoptic's init_pt_cld.npz."""
MAX_LISTED = 50
"""Most problems of one file listed; the rest are counted."""

M = TypeVar("M", bound=BaseModel)


class FieldError(ValueError):
    """A value of a parsed record that a reader cannot use: which field, and why."""

    def __init__(self, field: str, message: str):
        self.field, self.message = field, message
        super().__init__(f"{field}: {message}")


class Record(BaseModel):
    """A parsed source record: strict (JSON's types only: no strings for numbers), immutable,
    unknown keys kept (sources carry keys we do not interpret, and the import record keeps
    them)."""

    model_config = ConfigDict(strict=True, frozen=True, extra="allow")


def _custom(kind: str, message: str, **context: Any) -> PydanticCustomError:
    return PydanticCustomError(kind, message, context)


def _whole(value: float) -> int:
    if not float(value).is_integer():
        raise _custom("whole_number", "must be a whole number of pixels, got {value}",
                      value=value)
    return int(value)


def _name(value: str) -> str:
    problem = name_problem(value)
    if problem is not None:
        raise _custom("source_name", "{name}: {problem}", name=_short(value), problem=problem)
    return value


def _path(value: str) -> str:
    """A path relative to the source file's folder, '.' components dropped (NeRF synthetic
    writes ``./train/r_0``), that cannot leave that folder."""
    parts = [p for p in value.split("/") if p != "."]
    problem = path_problem("/".join(parts)) if parts else "names no file"
    if problem is not None:
        raise _custom("source_path", "{path} {problem}", path=_short(value), problem=problem)
    return "/".join(parts)


def _id_or_number(value: Any) -> int | str:
    if isinstance(value, bool) or not isinstance(value, (int, str)):
        raise _custom("id_or_number", "must be a whole number or a name, got {value}",
                      value=_short(value))
    return _name(value) if isinstance(value, str) else value


Number = Annotated[float, Field(allow_inf_nan=False)]
"""A finite number (an integer is one too); never a string."""
Side = Annotated[float, Field(gt=0, le=MAX_SIDE), AfterValidator(_whole)]
"""An image width or height: a positive whole number (1080.0 as instant-ngp writes it too)."""
SourceName = Annotated[str, AfterValidator(_name)]
"""A name that becomes a frame or camera id (`core.data.rules.name_problem`)."""
SourcePath = Annotated[str, AfterValidator(_path)]
"""A file the source names, relative to its folder and inside it (`core.data.rules`)."""
IdOrNumber = Annotated[int | str, PlainValidator(_id_or_number)]
"""A camera's number or name in its source (a name becomes an id: `SourceName`)."""


def listof(item: Any, most: int, least: int = 1) -> Any:
    """A list of `least` to `most` items."""
    return Annotated[list[item], Field(min_length=least, max_length=most)]


def matrix(rows: int, cols: int, least_rows: int | None = None) -> Any:
    """`rows` (or `least_rows` to `rows`) rows of `cols` numbers."""
    return listof(listof(Number, cols, cols), rows, rows if least_rows is None else least_rows)


def where(loc: Sequence[str | int]) -> str:
    """A pydantic location as a reader writes it: ``fn[0][3]``, ``frames[2].file_path``."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _short(value: Any, most: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= most else text[:most - 3] + "..."


def field_problems(path: Path, exc: ValidationError, prefix: str = "") -> list[Problem]:
    """One problem per error of `exc`, naming `path` and the field (at most `MAX_LISTED`)."""
    out = []
    for error in exc.errors(include_url=False)[:MAX_LISTED]:
        loc = where(error["loc"])
        # "frames[2].file_path", but "row 3: fx" and "line 7: camera_id" in text files
        sep = ": " if " " in prefix else "" if loc.startswith("[") else "."
        field = prefix + sep + loc if prefix and loc else prefix or loc
        message = "is missing" if error["type"] == "missing" else error["msg"]
        if error["type"] in ("json_invalid", "model_type"):
            message = f"cannot parse it: {message}" if error["type"] == "json_invalid" else \
                f"expected an object, got {_short(error['input'])}"
        elif not error["type"].startswith("source_") and error["type"] not in (
                "missing", "too_long", "too_short") and not isinstance(
                error["input"], (dict, list)):
            message += f", got {_short(error['input'])}"
        out.append(Problem(str(path), f"{field}: {message}" if field else message))
    if exc.error_count() > MAX_LISTED:
        out.append(Problem(str(path), f"and {exc.error_count() - MAX_LISTED} more problems"))
    return out


def checked(model: type[M] | TypeAdapter, value: Any, path: Path, prefix: str = "",
            problems: list[Problem] | None = None) -> Any:
    """`value` (Python data) as `model` (a record, or a `TypeAdapter` of a type made by the
    helpers here): None, with the problems added to `problems`, when it is not one
    (CaptureError when `problems` is None)."""
    try:
        if isinstance(model, TypeAdapter):
            return model.validate_python(value, strict=True)
        return model.model_validate(value)
    except ValidationError as exc:
        found = field_problems(path, exc, prefix)
    if problems is None:
        raise CaptureError(found)
    problems.extend(found)
    return None


def load_json(path: Path, model: type[M]) -> M:
    """The JSON file `path` parsed into `model`: its size and its count of values bounded
    before it is parsed (core.data.rules); CaptureError naming the file and each field."""
    try:
        data = read_bounded(path)
    except ValueError as exc:
        raise CaptureError([Problem(str(path), str(exc))]) from None
    problem = json_values_problem(data)
    if problem is not None:
        raise CaptureError([Problem(str(path), problem)])
    try:
        return model.model_validate_json(data)
    except ValidationError as exc:
        raise CaptureError(field_problems(path, exc)) from None


def read_text(path: Path, limit: int = MAX_METADATA_BYTES) -> str:
    """A text file (UTF-8) read under `limit`; CaptureError naming it otherwise."""
    try:
        return read_bounded(path, limit).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise CaptureError([Problem(str(path), f"is not UTF-8 text (byte {exc.start})")]) \
            from None
    except ValueError as exc:
        raise CaptureError([Problem(str(path), str(exc))]) from None


def load_npz(path: Path, *, limit: int = MAX_METADATA_BYTES,
             most: int = 4 * MAX_CAMERAS + 16) -> dict[str, np.ndarray]:
    """The arrays of a .npz archive, numbers only: its size (at most `limit`), its member
    count and each member's decompressed size are checked from the zip's directory before any
    array is loaded (an npz is a zip, and a zip can be a bomb); never unpickles."""
    try:
        size = path.stat().st_size
        if size > limit:
            raise ValueError(f"is {size} bytes; this file may have {limit}")
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
        if len(infos) > most:
            raise ValueError(f"holds {len(infos)} arrays; at most {most} are read")
        big = next((i for i in infos if i.file_size > MAX_ARRAY_BYTES), None)
        if big is not None:
            raise ValueError(f"{big.filename}: {big.file_size} bytes once decompressed; an "
                             f"array may have {MAX_ARRAY_BYTES}")
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: np.asarray(data[k]) for k in data.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error,
            NotImplementedError) as exc:
        raise CaptureError([Problem(str(path), f"cannot read as a .npz archive of arrays: "
                                    f"{_plain(exc)}")]) from None
    for key, arr in arrays.items():
        if arr.dtype.kind not in "biuf":
            raise CaptureError([Problem(str(path), f"{key}: must be an array of numbers, got "
                                        f"dtype {arr.dtype.str}")])
    return arrays


def _plain(exc: BaseException) -> str:
    """An exception's message without the file's path (callers name the file)."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


def stem(path: str) -> str:
    """A source path's last component without its extension (as `PurePosixPath.stem`, at
    string speed: a source names every view)."""
    name = path.rpartition("/")[2]
    dot = name.rfind(".")
    return name[:dot] if 0 < dot < len(name) - 1 else name
