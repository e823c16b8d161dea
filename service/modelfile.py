"""Normal-prior models clients upload (`POST /v1/assets?kind=normal_model`): a TorchScript
archive (what `torch.jit.save` writes: a zip with the model's code and pickled data) or an ONNX
protobuf. The API process has no torch, so it checks the container, not the model; a worker
that cannot load it fails the job with the reason."""

from __future__ import annotations

import zipfile
from pathlib import Path

__all__ = ["MODEL_CONTENT_TYPES", "ModelFileError", "inspect_model"]

MODEL_CONTENT_TYPES = {".pt": "application/octet-stream", ".ts": "application/octet-stream",
                       ".onnx": "application/onnx"}


class ModelFileError(ValueError):
    """The file is not a model this service can use; the message says why."""


def _torchscript(path: Path) -> dict:
    try:
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
    except (zipfile.BadZipFile, OSError):
        raise ModelFileError("not a TorchScript archive (torch.jit.save writes a zip file; "
                             "this is not one)") from None
    if not any(n.endswith("/data.pkl") for n in names) or \
            not any("/code/" in n for n in names):
        raise ModelFileError("a zip file, but not a TorchScript archive (no code/ and "
                             "data.pkl: save the model with torch.jit.save, not torch.save)")
    return {"format": "torchscript"}


def _onnx(path: Path) -> dict:
    with path.open("rb") as f:
        head = f.read(1)
    # An ONNX ModelProto starts with field 1 (ir_version), a varint: the tag byte 0x08.
    if head != b"\x08":
        raise ModelFileError("not an ONNX model (an ONNX file is a ModelProto that starts "
                             "with its ir_version)")
    return {"format": "onnx"}


def inspect_model(path: Path, suffix: str) -> dict:
    """The asset's metadata ({"format"}), or ModelFileError saying what is wrong."""
    if path.stat().st_size == 0:
        raise ModelFileError("empty file")
    return _onnx(path) if suffix == ".onnx" else _torchscript(path)
