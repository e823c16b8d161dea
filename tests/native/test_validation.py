"""Bad arguments raise ValueError naming the argument, before any native code runs."""

from __future__ import annotations

import pytest
import torch

from native import rasterize
from native.reference import rasterize as reference
from scenes import random_scene


def _args():
    return list(random_scene(10, 16, 12, seed=0).args())


INDEX = {"means": 0, "quats": 1, "scales": 2, "opacity_c": 3, "opacity_g": 4, "colors": 5,
         "geometry": 6, "viewmat": 7, "K": 8, "width": 9, "height": 10}


def _bad(name, make):
    args = _args()
    args[INDEX[name]] = make(args[INDEX[name]])
    return args


CASES = [
    ("means", lambda t: t[:, :2], "shape"),
    ("quats", lambda t: t[:5], "shape"),
    ("scales", lambda t: t.reshape(-1), "shape"),
    ("opacity_c", lambda t: t[:, None], "shape"),
    ("opacity_g", lambda t: t[:3], "shape"),
    ("colors", lambda t: t[:4], "shape"),
    ("geometry", lambda t: t[0], "shape"),
    ("viewmat", lambda t: t[:3], "shape"),
    ("K", lambda t: t[:2], "shape"),
    ("quats", lambda t: t.double(), "dtype"),
    ("colors", lambda t: t.half(), "dtype"),
    ("viewmat", lambda t: t.to(torch.float64), "dtype"),
    ("scales", lambda t: t.to("meta"), "meta"),
    ("scales", lambda t: t.t().contiguous().t(), "contiguous"),
    ("colors", lambda t: t.index_fill(0, torch.tensor([2]), float("nan")), "NaN"),
    ("K", lambda t: t.index_fill(0, torch.tensor([0]), float("inf")), "NaN or Inf"),
    ("scales", lambda t: -t, "positive"),
    ("opacity_c", lambda t: t + 1.5, "[0, 1]"),
    ("opacity_g", lambda t: t - 1.5, "[0, 1]"),
    ("quats", lambda t: t.index_fill(0, torch.tensor([1]), 0.0), "zero quaternion"),
    ("width", lambda t: -3, "non-negative integer"),
    ("height", lambda t: 12.5, "non-negative integer"),
    ("K", lambda t: t * torch.tensor([[-1.0], [1.0], [1.0]]), "focal"),
    ("means", lambda t: [[0.0, 0.0, 0.0]], "torch.Tensor"),
]


@pytest.mark.parametrize("impl", [rasterize, reference], ids=["native", "reference"])
@pytest.mark.parametrize("name,make,words", CASES, ids=[f"{c[0]}-{c[2]}" for c in CASES])
def test_bad_argument_is_named(impl, name, make, words):
    if impl is reference and words == "contiguous":
        pytest.skip("the reference accepts any layout")
    with pytest.raises(ValueError) as err:
        impl(*_bad(name, make))
    message = str(err.value)
    assert name in message, message
    assert words in message, message


@pytest.mark.parametrize("kw,name", [({"beta": 1.5}, "beta"), ({"eps2d": -0.1}, "eps2d"),
                                     ({"near": 0.0}, "near"), ({"near": 5.0, "far": 2.0}, "far"),
                                     ({"background": torch.zeros(2)}, "background"),
                                     ({"backend": "cuda"}, "backend")])
def test_bad_option_is_named(kw, name):
    with pytest.raises(ValueError, match=name):
        rasterize(*_args(), **kw)


def test_validate_false_checks_structure_not_values():
    # Shapes, dtypes and contiguity cost nothing and are always checked...
    with pytest.raises(ValueError, match="contiguous"):
        rasterize(*_bad("scales", lambda t: t.t().contiguous().t()), validate=False)
    with pytest.raises(ValueError, match="shape"):
        rasterize(*_bad("quats", lambda t: t[:5]), validate=False)
    with pytest.raises(ValueError, match="NaN or Inf"):  # K and viewmat: a few numbers each
        rasterize(*_bad("K", lambda t: t.index_fill(0, torch.tensor([0]), float("inf"))),
                  validate=False)
    # ...the per-element values only when asked (a training loop checks them once per run),
    # and the kernels cull a Gaussian with a non-finite or degenerate value without harm.
    bad = _bad("means", lambda t: t.index_fill(0, torch.tensor([3]), float("nan")))
    out = rasterize(*bad, validate=False)
    clean = _args()
    keep = torch.arange(len(clean[0])) != 3
    ref = rasterize(*[a[keep] if i < 7 else a for i, a in enumerate(clean)])
    assert out.radii[3] == 0
    torch.testing.assert_close(out.color, ref.color, atol=1e-6, rtol=1e-5)
