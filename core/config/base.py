"""What every configuration section shares: frozen pydantic dataclasses that validate strictly
(no strings for numbers, no booleans for integers, no NaN or infinity, no unknown keys), and one
way of turning a validation failure into messages that name the setting.

Torch-free: the API process validates a job's configuration with these before the job exists.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import re
import typing
from collections.abc import Callable
from typing import Annotated, Any, TypeVar

from pydantic import (
    AfterValidator,
    BeforeValidator,
    BaseModel,
    ConfigDict,
    Field,
    TypeAdapter,
    ValidationError,
)
from pydantic.dataclasses import dataclass as pydantic_dataclass
from pydantic_core import PydanticCustomError

__all__ = ["AsTuple", "ConfigError", "Device", "FRAMES", "FrameSlice", "Fraction", "Positive",
           "Steps", "StrictModel", "Weight", "section", "validate"]

T = TypeVar("T")

STRICT = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False,
                    use_attribute_docstrings=True)
"""The one strictness of everything a user or a client configures: the run configuration's
sections, and (through `StrictModel`) every request body and job's parameters of the service."""

# Upper bounds a request cannot exceed. They are far beyond any run that makes sense (the paper
# preset is 30k steps; a 4 MP studio frame stays under a few million Gaussians) and low enough
# that a typo cannot hold a worker for days.
MAX_STEPS = 300_000

Steps = Annotated[int, Field(ge=0, le=MAX_STEPS)]
"""A step count or interval."""
Positive = Annotated[float, Field(gt=0, le=1e6)]
"""A finite number > 0."""
Weight = Annotated[float, Field(ge=0, le=1e4)]
"""A loss weight (0 turns the term off)."""
Fraction = Annotated[float, Field(ge=0, le=1)]
"""A number in [0, 1]."""
DEVICE_PATTERN = r"^(auto|cpu|cuda(:\d{1,2})?)$"


def _device(value: str) -> str:
    if not re.match(DEVICE_PATTERN, value):
        raise ValueError(f"expected auto, cpu, cuda or cuda:N, got {value!r}")
    return value


Device = Annotated[str, AfterValidator(_device), Field(json_schema_extra={
    "pattern": DEVICE_PATTERN})]
"""A torch device as configuration names it (whether it exists is `core.device`'s question)."""

_INDEX = r"-?\d{1,6}"
FRAMES = rf"^{_INDEX}$|^({_INDEX})?:({_INDEX})?(:({_INDEX})?)?$"
"""A Python slice over a frame list ('0:10', '2', '::2', '-5:'), each number at most 6 digits
(a million frames): a number nothing can mean is refused, not clamped by `slice`."""


def _frame_slice(value: str) -> str:
    if not re.match(FRAMES, value):
        raise PydanticCustomError(
            "frame_slice", "expected a Python slice over the frame list: A, A:B or A:B:S, "
            "each a whole number of at most 6 digits, got {value}",
            {"value": json.dumps(value[:40])})
    parts = value.split(":")
    if len(parts) == 3 and parts[2] and int(parts[2]) == 0:
        raise PydanticCustomError("frame_slice", "a slice's step must not be 0, got {value}",
                                  {"value": json.dumps(value)})
    return value


FrameSlice = Annotated[str, AfterValidator(_frame_slice), Field(
    max_length=32, json_schema_extra={"pattern": FRAMES})]
"""A frame slice as a request or the command line gives it (whether it selects anything is a
question for the capture: `core.config.parse_frames`)."""


def _as_tuple(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


AsTuple = BeforeValidator(_as_tuple)
"""On a tuple field of a StrictModel (`Annotated[tuple[...], AsTuple]`): a list is taken for
it from Python too, as JSON gives one (strict mode wants a tuple there); its items are checked
as strictly as ever. A field validator, not a model one: a model's `before` validator hands
the whole input back as Python, where strict mode refuses a time written as text."""


class StrictModel(BaseModel):
    """A pydantic model validated as strictly as the configuration sections (`STRICT`): no
    strings or booleans for numbers, no NaN or infinity, no unknown keys. Validate JSON data
    with `validate`, which goes through JSON (an ISO string for a time), or with
    `model_validate_json`; tuple fields are `AsTuple`."""

    model_config = STRICT


def section(cls: type[T]) -> type[T]:
    """A frozen, strictly validated configuration dataclass (`dataclasses.replace`, `asdict` and
    `fields` work on it as on any dataclass). Building one validates: a bad value raises
    ConfigError naming the field."""
    cls = pydantic_dataclass(frozen=True, config=STRICT)(cls)
    init = cls.__init__

    @functools.wraps(init)
    def __init__(self, *args, **kwargs) -> None:
        try:
            init(self, *args, **kwargs)
        except ValidationError as exc:
            raise ConfigError(errors_of(exc, type(self))) from None

    cls.__init__ = __init__
    return cls


class ConfigError(ValueError):
    """Invalid configuration: `details` lists {"path", "message"} per problem; the message is
    the first one, "path: message"."""

    def __init__(self, details: list[dict[str, str]]):
        self.details = details
        first = details[0]
        more = f" (+{len(details) - 1} more)" if len(details) > 1 else ""
        super().__init__(f"{first['path']}: {first['message']}{more}")


def _field_type(cls: Any, name: str) -> Any:
    """The declared type of field `name` of dataclass or model `cls` (None when there is
    none)."""
    if isinstance(cls, type) and issubclass(cls, BaseModel):
        field = cls.model_fields.get(name)
        return None if field is None else field.annotation
    if not dataclasses.is_dataclass(cls):
        return None
    hints = typing.get_type_hints(cls)
    return hints.get(name)


def _names(cls: Any) -> list[str]:
    if isinstance(cls, type) and issubclass(cls, BaseModel):
        return sorted(cls.model_fields)
    return sorted(f.name for f in dataclasses.fields(cls)) if dataclasses.is_dataclass(cls) \
        else []


def _known_keys(root: Any, loc: tuple) -> list[str]:
    """The setting names of the section at `loc` (walking dataclass fields from `root`)."""
    cls = root
    for part in loc:
        cls = _field_type(cls, part) if isinstance(part, str) else None
        while typing.get_origin(cls) is Annotated:
            cls = typing.get_args(cls)[0]
    return _names(cls)


def _message(error: dict, root: Any) -> str:
    kind, loc = error["type"], tuple(error["loc"])
    if kind in ("unexpected_keyword_argument", "extra_forbidden"):
        known = _known_keys(root, loc[:-1])
        return "unknown setting" + (f" (known: {', '.join(known)})" if known else "")
    message = error["msg"].removeprefix("Value error, ")
    value = error.get("input")
    if kind != "value_error" and isinstance(value, (bool, int, float, str)) and \
            len(repr(value)) <= 40 and ", got " not in message:
        message += f", got {json.dumps(value)}"
    return message


def _path(loc: tuple, where: str) -> str:
    text = where
    for part in loc:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "config"


def errors_of(exc: ValidationError, root: Any, where: str = "") -> list[dict[str, str]]:
    """{"path", "message"} per problem of a pydantic validation of `root` (paths under
    `where`)."""
    out = []
    for error in exc.errors(include_url=False):
        # A failed check across fields reports the section; its message names the fields.
        out.append({"path": _path(tuple(error["loc"]), where),
                    "message": _message(error, root)})
    return out


_ADAPTERS: dict[Any, TypeAdapter] = {}


def adapter(cls: Any) -> TypeAdapter:
    if cls not in _ADAPTERS:
        _ADAPTERS[cls] = TypeAdapter(cls)
    return _ADAPTERS[cls]


def validate(cls: type[T], data: Any, where: str = "") -> T:
    """An instance of section `cls` from JSON-like `data` (dicts, lists, numbers, strings,
    None); ConfigError naming each bad setting (under `where`) otherwise. Validation is strict
    and goes through JSON, so a tuple field takes a list and NaN or infinity is refused."""
    try:
        text = json.dumps(data, allow_nan=True)
    except (TypeError, ValueError) as exc:
        raise ConfigError([{"path": where or "config",
                            "message": f"not JSON data ({exc})"}]) from None
    try:
        return adapter(cls).validate_json(text)
    except ValidationError as exc:
        raise ConfigError(errors_of(exc, cls, where)) from None


def schema(cls: Any, *, inline: bool = False) -> dict[str, Any]:
    """The JSON Schema of section `cls` (every field has a default, so any subset of the keys is
    a valid override); `inline`: its sections written out in place instead of `$ref`s, for
    embedding in another document (an OpenAPI property)."""
    doc = adapter(cls).json_schema()
    if not inline:
        return doc
    defs = doc.pop("$defs", {})

    def expand(node: Any) -> Any:
        if isinstance(node, dict):
            if "$ref" in node:
                target = expand(defs[node["$ref"].rsplit("/", 1)[-1]])
                return {**target, **{k: expand(v) for k, v in node.items() if k != "$ref"}}
            return {k: expand(v) for k, v in node.items()}
        if isinstance(node, list):
            return [expand(v) for v in node]
        return node

    return expand(doc)


def checked(build: Callable[[], T], root: Any, where: str = "") -> T:
    """`build()`, with a pydantic ValidationError it raises turned into ConfigError."""
    try:
        return build()
    except ValidationError as exc:
        raise ConfigError(errors_of(exc, root, where)) from None
