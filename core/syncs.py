"""Host reads of device values, counted where they are made (`SyncCounter`): on a GPU each one
(`.item()`, `float()`, `bool()`, `.tolist()`, `.cpu()`, `.numpy()`, `nonzero`, indexing with a
boolean mask, a tensor made from host data) waits for every queued kernel, while on the CPU it
costs nothing, so a loop written on the CPU hides them. `benchmarks/step_profile.py` prints
them per step; tests/core/test_step_syncs.py holds the training steps to none."""

from __future__ import annotations

import collections
import traceback
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode

__all__ = ["HOST_ONLY", "SyncCounter"]

ROOT = Path(__file__).resolve().parents[1]

# Reads of a device value on the host (a device sync on CUDA).
SYNC_METHODS = {"item", "tolist", "numpy", "cpu", "__bool__", "__float__", "__int__",
                "__index__", "nonzero", "unique"}
# Reads that stay on the host on a GPU too, by where they are made: Adam's step counters are
# CPU tensors (torch.optim, not fused or capturable), the view order is drawn on the CPU
# generator, and the rasterizer's settings checks run on the CPU only (on CUDA, after a frame's
# first render, they read nothing: native/_validate.py).
HOST_ONLY = ("torch/optim/", "core/training/loop.py:next_view", "native/_validate.py")


class SyncCounter(TorchFunctionMode):
    """Counts host reads of tensor values (and tensors made from host data, a copy to the
    device on a GPU) while active (`with SyncCounter() as c:`), each with the line of core/ or
    native/ it comes from (`by_line`); reads that stay on the host on a GPU too (`HOST_ONLY`)
    apart (`host_only`)."""

    def __init__(self):
        super().__init__()
        self.by_kind: collections.Counter = collections.Counter()
        self.by_line: collections.Counter = collections.Counter()
        self.host_only = 0

    @property
    def syncs(self) -> int:
        """Reads that wait for the device on a GPU."""
        return sum(self.by_kind.values())

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        kind = None
        if name in SYNC_METHODS:
            kind = name.strip("_")
        elif name == "tensor" and (kwargs or {}).get("device") is not None:
            kind = "host data to device"
        elif name == "__getitem__" and len(args) > 1 and _bool_index(args[1]):
            kind = "bool-mask index"
        elif name == "__setitem__" and len(args) > 1 and _bool_index(args[1]):
            kind = "bool-mask assign"
        if kind is not None:
            site = _caller()
            if any(h in site for h in HOST_ONLY):
                self.host_only += 1
            else:
                self.by_kind[kind] += 1
                self.by_line[f"{kind} @ {site}"] += 1
        return func(*args, **(kwargs or {}))


def _bool_index(index) -> bool:
    items = index if isinstance(index, tuple) else (index,)
    return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in items)


def _caller() -> str:
    """The innermost line of ours (core/, native/) that led here, with its function, and
    "torch/optim/" in front when the read is the optimizer's own."""
    via = ""
    for frame in reversed(traceback.extract_stack()[:-2]):
        path = Path(frame.filename)
        if "optim" in path.parts and "torch" in path.parts:
            via = "torch/optim/ from "
        if ROOT in path.parents and path.parts[len(ROOT.parts)] in ("core", "native"):
            return f"{via}{path.relative_to(ROOT)}:{frame.name}:{frame.lineno}"
    return via + "?"
