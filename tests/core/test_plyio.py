"""core.plyio, the one PLY reader and writer: the three layouts (Gaussians, seed points, meshes)
round-trip, ASCII and big-endian files read like binary little-endian ones, and every bad file
is refused with its name and the problem."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.plyio import (
    gaussian_ply_properties,
    read_gaussian_ply,
    read_mesh_ply,
    read_point_ply,
    read_track_ids,
    write_gaussian_ply,
    write_mesh_ply,
    write_point_ply,
)

SHAPES = {"means": (3,), "scales": (3,), "quats": (4,), "sh0": (1, 3), "shN": (15, 3),
          "opacity_c": (), "opacity_g": (), "normals": (3,), "visibility": (1,)}


def _params(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {k: rng.normal(size=(n, *shape)).astype(np.float32) for k, shape in SHAPES.items()}


def _header(fmt: str, count: int, props: list[tuple[str, str]], extra: str = "") -> bytes:
    lines = ["ply", f"format {fmt} 1.0", "comment made by hand", f"element vertex {count}"]
    lines += [f"property {t} {n}" for n, t in props]
    return ("\n".join(lines) + "\n" + extra + "end_header\n").encode()


def test_gaussians_round_trip_bit_exact_with_the_3dgs_header(tmp_path: Path):
    params, ids = _params(5), np.array([4, 0, 7, 2**31 - 1, 3])
    path = tmp_path / "g.ply"
    write_gaussian_ply(path, params, ids)
    back = read_gaussian_ply(path)
    for name, value in params.items():
        np.testing.assert_array_equal(back[name], value.reshape(back[name].shape), name)
    np.testing.assert_array_equal(read_track_ids(path), ids)
    raw = path.read_bytes()
    head = raw[:raw.index(b"end_header\n")].decode().splitlines()
    assert head[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 5"]
    assert head[3:] == [f"property float {p}" for p in gaussian_ply_properties()] + [
        "property int track_id"]
    write_gaussian_ply(tmp_path / "plain.ply", params)
    assert read_track_ids(tmp_path / "plain.ply") is None
    with pytest.raises(ValueError, match="track_ids: expected 5 ids"):
        write_gaussian_ply(path, params, np.arange(4))


def test_gaussians_from_ascii_and_big_endian_files(tmp_path: Path):
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    values = np.arange(2 * len(names), dtype=np.float64).reshape(2, len(names))
    ascii_file = tmp_path / "a.ply"
    ascii_file.write_bytes(_header("ascii", 2, [(n, "double") for n in names])
                           + b"".join(" ".join(map(str, r)).encode() + b"\n" for r in values))
    big = tmp_path / "b.ply"
    big.write_bytes(_header("binary_big_endian", 2, [(n, "float") for n in names])
                    + values.astype(">f4").tobytes())
    for path in (ascii_file, big):
        g = read_gaussian_ply(path)
        np.testing.assert_array_equal(g["means"], values[:, :3])
        np.testing.assert_array_equal(g["quats"], values[:, 10:14])
        assert g["shN"].shape == (2, 15, 3) and not g["shN"].any()
        np.testing.assert_array_equal(g["opacity_g"], g["opacity_c"])


@pytest.mark.parametrize("content,words", [
    (b"not a ply", "not a PLY file"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n",
     "not a PLY file"),
    (_header("binary_little_endian", 3, [(n, "float") for n in "xyz"]) + b"\0" * 20,
     "truncated: element 'vertex' has 1 of its 3 rows"),
    (_header("binary_little_endian", 1, [("x", "int64")]), "int64"),
    (_header("binary_little_endian", 1, [(n, "float") for n in "xyz"]) + b"\0" * 12,
     "lacks vertex properties"),
    (_header("ascii", 1, [("x", "float"), ("y", "float")]) + b"1 oops\n", "malformed input"),
])
def test_bad_gaussian_files_are_named(tmp_path: Path, content: bytes, words: str):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(ValueError, match="path: ") as err:
        read_gaussian_ply(path)
    assert str(path) in str(err.value) and words in str(err.value), err.value


def test_points_colours_as_bytes_or_floats_and_other_elements_ignored(tmp_path: Path):
    points = np.array([[0.5, 1.0, -2.0], [3.0, 4.0, 5.0]])
    write_point_ply(tmp_path / "p.ply", points, np.array([[1.0, 0.0, 0.5], [0.2, 0.4, 0.6]]))
    back, colors = read_point_ply(tmp_path / "p.ply")
    np.testing.assert_array_equal(back, points)
    np.testing.assert_allclose(colors, [[1, 0, 128 / 255], [51 / 255, 102 / 255, 153 / 255]])
    faces = "element face 1\nproperty list uchar int vertex_indices\n"
    floats = tmp_path / "f.ply"
    floats.write_bytes(_header("binary_little_endian", 1, [(n, "double") for n in "xyz"]
                               + [(c, "float") for c in ("red", "green", "blue")], faces)
                       + np.array([1, 2, 3], "<f8").tobytes()
                       + np.array([0.25, 2.0, -1], "<f4").tobytes()
                       + b"\x03" + np.array([0, 0, 0], "<i4").tobytes())
    back, colors = read_point_ply(floats)
    np.testing.assert_array_equal(back, [[1, 2, 3]])
    np.testing.assert_array_equal(colors, [[0.25, 1.0, 0.0]])
    grey = tmp_path / "grey.ply"
    write_point_ply(grey, points)
    assert (read_point_ply(grey)[1] == 128 / 255).all()
    nan = tmp_path / "nan.ply"
    write_point_ply(nan, np.array([[np.nan, 0, 0]]))
    with pytest.raises(ValueError, match="NaN"):
        read_point_ply(nan)


def test_meshes_round_trip_and_only_triangles_are_read(tmp_path: Path):
    rng = np.random.default_rng(1)
    vertices = rng.normal(size=(6, 3)).astype(np.float32)
    faces = np.array([[0, 1, 2], [3, 4, 5], [0, 2, 4]])
    write_mesh_ply(tmp_path / "m.ply", vertices, faces, vertices)
    v, f = read_mesh_ply(tmp_path / "m.ply")
    np.testing.assert_array_equal(v, vertices)
    np.testing.assert_array_equal(f, faces)
    assert v.dtype == np.float64 and f.dtype == np.int64
    quad = tmp_path / "quad.ply"
    quad.write_bytes(_header("binary_little_endian", 4, [(n, "float") for n in "xyz"],
                             "element face 1\nproperty list uchar int vertex_indices\n")
                     + b"\0" * 48 + b"\x04" + b"\0" * 16)
    with pytest.raises(ValueError, match="quad.ply: element 'face' row 0: only triangles"):
        read_mesh_ply(quad)
    write_point_ply(tmp_path / "points.ply", vertices)
    with pytest.raises(ValueError, match="points.ply: a mesh needs 'vertex' and 'face'"):
        read_mesh_ply(tmp_path / "points.ply")
    with pytest.raises(ValueError, match="missing.ply: cannot read"):
        read_mesh_ply(tmp_path / "missing.ply")
