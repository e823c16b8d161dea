"""IDR / NeuS `cameras.npz` captures: a round trip through the projection matrices, the
normalised world, and the skew rule (negligible skew dropped with a note, a larger one refused
with its size)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.data import CaptureError, detect_format, import_capture, load_capture, validate_capture
from core.data.importers.idr import SKEW_TOLERANCE, decompose_projection, drop_skew, export_idr


def _scale_mat() -> np.ndarray:
    S = np.diag([1.7, 1.7, 1.7, 1.0])
    S[:3, 3] = [0.1, -0.2, 0.9]
    return S


def test_round_trip_in_the_normalised_world(synth_capture: Path, tmp_path: Path, digest):
    source = load_capture(synth_capture)
    S = _scale_mat()
    export_idr(source, tmp_path / "scan", scale_mat=S)
    assert detect_format(tmp_path / "scan") == "idr"
    before = digest(tmp_path / "scan")
    out = import_capture(tmp_path / "scan", tmp_path / "imported")
    assert digest(tmp_path / "scan") == before, "import modified its source"
    assert validate_capture(out.root) == []
    record = out.import_record
    assert record["format"] == "idr" and record["notes"] == {}
    np.testing.assert_allclose(record["to_source"]["source_from_world"], S)
    assert len(out.cameras) == len(source.cameras) and out.frames == ("000000",)
    # A world point lands on the same pixel through the source camera and, carried into the
    # normalised world by inv(scale_mat), through the imported one.
    rng = np.random.default_rng(0)
    world = rng.normal(0, 0.3, (20, 3)) + [0, 0, 0.9]
    normalised = (np.linalg.inv(S) @ np.c_[world, np.ones(20)].T).T[:, :3]
    for a, b in zip(source.cameras, out.cameras):
        assert (a.width, a.height) == (b.width, b.height)
        np.testing.assert_allclose(a.K, b.K, atol=1e-9)
        np.testing.assert_allclose(a.project(world)[0], b.project(normalised)[0], atol=1e-7)
        np.testing.assert_allclose(np.linalg.det(b.R), 1.0, atol=1e-9)
    # Images and masks travel with their camera.
    frame = source.frames[0]
    for a, b in zip(source.cameras, out.cameras):
        assert out.image_path("000000", b.id).read_bytes() == \
            source.image_path(frame, a.id).read_bytes()
        assert out.mask_path("000000", b.id).read_bytes() == \
            source.mask_path(frame, a.id).read_bytes()


def test_decomposition_of_any_scale_and_sign():
    rng = np.random.default_rng(1)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.diag(r))
    R = R if np.linalg.det(R) > 0 else -R
    K = np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
    t = np.array([0.1, -0.3, 2.0])
    for scale in (1.0, 3.5, -0.02):
        Kd, w2c = decompose_projection(scale * K @ np.c_[R, t])
        np.testing.assert_allclose(Kd, K, atol=1e-9)
        np.testing.assert_allclose(w2c[:3, :3], R, atol=1e-12)
        np.testing.assert_allclose(w2c[:3, 3], t, atol=1e-12)


def test_skew_rule():
    K = np.array([[1000.0, 0.0, 500.0], [0.0, 1000.0, 400.0], [0.0, 0.0, 1.0]])
    small = K.copy()
    small[0, 1] = 0.5 * SKEW_TOLERANCE * 1000.0
    kept, note = drop_skew(small)
    assert kept[0, 1] == 0.0 and note is not None and "dropped" in note and "0.5 px" in note
    assert drop_skew(K)[1] is None
    large = K.copy()
    large[0, 1] = 2.5
    with pytest.raises(ValueError, match=r"skew of 2\.5 px \(0\.0025 of fx"):
        drop_skew(large)


def _with_skew(src: Path, index: int, skew: float) -> None:
    path = src / "cameras.npz"
    data = dict(np.load(path))
    world = data[f"world_mat_{index}"].copy()
    # P = K [R | t]: add skew to K, i.e. skew x (row 1 of [R | t]) to row 0 of P.
    Kd, w2c = decompose_projection(world[:3])
    Kd[0, 1] = skew
    world[:3, :4] = Kd @ w2c[:3]
    data[f"world_mat_{index}"] = world
    np.savez(path, **data)


def test_skew_on_import(synth_capture: Path, tmp_path: Path):
    source = load_capture(synth_capture)
    export_idr(source, tmp_path / "scan")
    fx = source.cameras[2].K[0, 0]
    _with_skew(tmp_path / "scan", 2, 1e-4 * fx)
    out = import_capture(tmp_path / "scan", tmp_path / "ok")
    cam = out.cameras[2]
    assert cam.K[0, 1] == 0.0
    assert "dropped" in out.import_record["notes"][cam.id]
    _with_skew(tmp_path / "scan", 3, 0.01 * fx)
    with pytest.raises(CaptureError) as err:
        import_capture(tmp_path / "scan", tmp_path / "refused")
    message = str(err.value)
    assert "cameras.npz" in message and "camera 3" in message and "0.01 of fx" in message
    assert not (tmp_path / "refused").exists()


def test_idr_errors_name_the_file(synth_capture: Path, tmp_path: Path):
    source = load_capture(synth_capture)
    export_idr(source, tmp_path / "scan")
    data = dict(np.load(tmp_path / "scan" / "cameras.npz"))
    del data["world_mat_1"]
    np.savez(tmp_path / "scan" / "cameras.npz", **data)
    with pytest.raises(CaptureError, match="world_mat_1: is missing"):
        import_capture(tmp_path / "scan", tmp_path / "out")
    (tmp_path / "scan" / "cameras.npz").write_bytes(b"not an archive")
    with pytest.raises(CaptureError, match="cannot read as a .npz"):
        import_capture(tmp_path / "scan", tmp_path / "out")
