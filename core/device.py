"""Which torch device training and rendering run on, and moving nested state between devices.

A device is named as in configuration and on the command line: ``auto`` (CUDA when torch sees a
GPU and the native extension builds its CUDA kernels, `native._backend.cuda_build`; else the
CPU), ``cpu``, ``cuda`` or ``cuda:N``. The environment variable ``DGS_DEVICE``, when set, is what
``auto`` stands for (the test suite sets it to ``cpu``: its exact-resume checks hold on the CPU,
while CUDA's atomic gradient sums are not bit-reproducible); explicit names ignore it.
Checkpoints are written with every tensor on the CPU (`to_device(blob, "cpu")`), so one written
on a GPU resumes on a CPU and the other way round.
"""

from __future__ import annotations

import os
import re

import torch
from torch import Tensor

from core.config import DEVICE_PATTERN
from native._backend import cuda_build

__all__ = ["DEVICE_CHOICES", "check_device_spec", "resolve_device", "to_device"]

DEVICE_CHOICES = "auto, cpu, cuda or cuda:N"
_SPEC = re.compile(DEVICE_PATTERN)


def check_device_spec(spec: object, where: str = "device") -> str:
    """`spec` when it is a device name this package accepts (its syntax only: whether CUDA is
    there is `resolve_device`'s question); ValueError naming `where` otherwise."""
    if not isinstance(spec, str) or not _SPEC.match(spec):
        raise ValueError(f"{where}: expected {DEVICE_CHOICES}, got {spec!r}")
    return spec


def _cuda_problem() -> str | None:
    """Why CUDA cannot be used here, or None when it can."""
    if torch.version.cuda is None:
        return "this torch is a CPU-only build"
    if not torch.cuda.is_available():
        return "torch sees no CUDA GPU"

    if not cuda_build():
        return ("the native extension would be built without its CUDA kernels (no nvcc found "
                "through torch's CUDA_HOME, or DGS_CUDA=0)")
    return None


def resolve_device(spec: str | torch.device = "auto", where: str = "device") -> torch.device:
    """The torch device `spec` stands for: ``auto`` is $DGS_DEVICE when set, else ``cuda`` when
    CUDA is usable (torch sees a GPU and the native extension has CUDA kernels), else ``cpu``.
    Asking for CUDA where it is not usable, or for a GPU index beyond those present, raises
    ValueError saying why."""
    if isinstance(spec, torch.device):
        spec = str(spec)
    spec = check_device_spec(spec, where)
    if spec == "auto" and os.environ.get("DGS_DEVICE", "auto") != "auto":
        return resolve_device(os.environ["DGS_DEVICE"], "DGS_DEVICE")
    if spec == "cpu":
        return torch.device("cpu")
    problem = _cuda_problem()
    if spec == "auto":
        return torch.device("cpu") if problem else resolve_device("cuda", where)
    if problem:
        raise ValueError(f"{where}: {spec!r} asked for, but {problem}; use --device cpu "
                         "(or auto)")
    device = torch.device(spec)
    count = torch.cuda.device_count()
    if device.index is not None and device.index >= count:
        raise ValueError(f"{where}: {spec!r} asked for, but torch sees {count} CUDA GPU(s) "
                         f"(cuda:0..cuda:{count - 1})")
    # An explicit index: tensors report cuda:N, and comparing devices must agree with them.
    return device if device.index is not None else torch.device("cuda",
                                                                torch.cuda.current_device())


def to_device(obj, device: torch.device | str):
    """`obj` with every tensor inside (dicts, lists, tuples, nested) moved to `device`; other
    values as they are. A tensor already there is returned as is (no copy)."""
    if isinstance(obj, Tensor):
        return obj.to(device)
    if isinstance(obj, dict):
        return {k: to_device(v, device) for k, v in obj.items()}
    if isinstance(obj, list):
        return [to_device(v, device) for v in obj]
    if isinstance(obj, tuple):
        return tuple(to_device(v, device) for v in obj)
    return obj
