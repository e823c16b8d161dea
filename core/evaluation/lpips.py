"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual
Metric"), version 0.1 with the AlexNet trunk: what the papers this project compares with report.

The calibrated linear layers ship inside the `lpips` package (weights/v0.1/alex.pth); the
trunk's ImageNet weights are torchvision's AlexNet (`alexnet-owt-7be5be79.pth`), which cannot
be downloaded at run time on every machine: LPIPS is scored when `DGS_LPIPS_WEIGHTS` names that
file, and is null otherwise. The `lpips` package imports torchvision, which does not load beside
the CPU build of torch this project pins, so the package is read as data (its weights file) and
the network is written here after its definition (lpips/pretrained_networks.py `alexnet`,
lpips/lpips.py `LPIPS.forward`): inputs in [-1, 1], shifted and scaled per channel, the ReLU
outputs of AlexNet's five convolutions, each unit-normalised over channels, squared
differences weighted by the linear layers, averaged over the image, summed over the layers.
"""

from __future__ import annotations

import importlib.util
import os
import pickle
from pathlib import Path

import numpy as np
import torch
from torch import nn

__all__ = ["ENV", "MIN_SIZE", "Lpips", "lin_weights", "load_lpips"]

ENV = "DGS_LPIPS_WEIGHTS"
"""The environment variable naming torchvision's AlexNet weights (a state dict with
`features.N.weight` / `.bias`)."""

# LPIPS v0.1's ScalingLayer: (x - shift) / scale per RGB channel.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
# (in, out, kernel, stride, padding) of AlexNet's convolutions, at torchvision's feature indices.
_CONVS = {0: (3, 64, 11, 4, 2), 3: (64, 192, 5, 1, 2), 6: (192, 384, 3, 1, 1),
          8: (384, 256, 3, 1, 1), 10: (256, 256, 3, 1, 1)}
_TAPS = (1, 4, 7, 9, 11)  # the five ReLUs whose outputs LPIPS compares
MIN_SIZE = 31
"""Smallest image side AlexNet's strides and poolings leave a feature of (11/4, 3/2, 3/2)."""


def lin_weights() -> Path | None:
    """The linear layers' file inside the installed `lpips` package (found without importing
    it), or None when the package is not installed."""
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(next(iter(spec.submodule_search_locations))) / "weights" / "v0.1" / "alex.pth"
    return path if path.is_file() else None


class Lpips(nn.Module):
    """LPIPS v0.1 (AlexNet) of two images (module docstring)."""

    def __init__(self):
        super().__init__()
        layers: list[nn.Module] = []
        for i in range(12):
            if i in _CONVS:
                cin, cout, k, s, p = _CONVS[i]
                layers.append(nn.Conv2d(cin, cout, k, stride=s, padding=p))
            elif i in (2, 5):
                layers.append(nn.MaxPool2d(3, stride=2))
            else:
                layers.append(nn.ReLU())
        self.features = nn.Sequential(*layers)
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in (64, 192, 384, 256, 256))
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def load(self, trunk: dict, lins: dict) -> Lpips:
        """Weights from torchvision's AlexNet state dict and lpips' alex.pth."""
        wanted = {f"features.{i}.{p}" for i in _CONVS for p in ("weight", "bias")}
        missing = sorted(wanted - set(trunk))
        if missing:
            raise ValueError(f"{ENV}: not an AlexNet state dict (missing {', '.join(missing[:3])})")
        self.features.load_state_dict({k[len("features."):]: v for k, v in trunk.items()
                                       if k in wanted})
        for i, lin in enumerate(self.lins):
            lin.weight.copy_(lins[f"lin{i}.model.1.weight"])
        return self

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in _TAPS:
                out.append(x / (x.square().sum(dim=1, keepdim=True).sqrt() + 1e-10))
        return out

    @torch.no_grad()
    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """(B,) distances of (B, 3, H, W) images in 0..1."""
        fa, fb = (self._taps(((2 * x - 1) - self.shift) / self.scale) for x in (a, b))
        return sum(lin((x - y).square()).mean(dim=(1, 2, 3)) for lin, x, y in
                   zip(self.lins, fa, fb))

    def score(self, a: np.ndarray, b: np.ndarray) -> float | None:
        """LPIPS of two (H, W, 3) images in 0..1; None for an image under `MIN_SIZE` pixels on
        a side (AlexNet's pooling leaves nothing of it)."""
        if min(a.shape[:2]) < MIN_SIZE:
            return None
        def t(x: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(x, np.float32)).permute(2, 0, 1)[None]

        return float(self(t(a), t(b))[0])


def load_lpips(trunk: str | os.PathLike[str] | None = None) -> Lpips | None:
    """LPIPS with the trunk weights at `trunk` (default $DGS_LPIPS_WEIGHTS), or None when no
    trunk is named or the lpips package is not installed; ValueError when a named file is not
    readable as AlexNet weights."""
    path = trunk if trunk is not None else os.environ.get(ENV) or None
    lins = lin_weights()
    if path is None or lins is None:
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, ValueError, pickle.UnpicklingError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"{ENV}: cannot read {Path(path).name} as torch weights: "
                         f"{first}") from None
    if not isinstance(state, dict):
        raise ValueError(f"{ENV}: {Path(path).name} is not a state dict")
    return Lpips().load(state, torch.load(lins, map_location="cpu", weights_only=True))
