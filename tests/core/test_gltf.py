"""A skinned, animated glTF character (core.synth.gltf) built here by hand: a two-bone bar whose
upper bone turns a quarter about the glTF z axis over a second. Skinning, interpolation,
normals, the turn to +Z up, texture sampling, looping, the refusals, and `dgs synth --subject`
filming it."""

from __future__ import annotations

import io
import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from core.synth.gltf import ALBEDO_SCALE, GltfCharacter, sample_texture
from core.color import srgb_to_linear

TEXELS = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [255, 255, 255]]], np.uint8)


def _bar() -> dict[str, np.ndarray]:
    """A square bar along glTF +y from 0 to 2 (four rings of four vertices), weights by height."""
    ring = np.array([[0.1, 0, 0.1], [-0.1, 0, 0.1], [-0.1, 0, -0.1], [0.1, 0, -0.1]])
    heights = [0.0, 0.9, 1.1, 2.0]
    pos = np.concatenate([ring + [0, h, 0] for h in heights])
    normals = np.concatenate([ring / np.linalg.norm(ring, axis=1, keepdims=True)] * 4)
    faces = []
    for r in range(3):
        for k in range(4):
            a, b = r * 4 + k, r * 4 + (k + 1) % 4
            faces += [[a, b, b + 4], [a, b + 4, a + 4]]
    upper = (pos[:, 1] > 1.0).astype(np.float32)
    weights = np.stack([1 - upper, upper, 0 * upper, 0 * upper], axis=1)
    joints = np.tile(np.array([0, 1, 0, 0], np.uint8), (len(pos), 1))
    uv = np.stack([np.linspace(0.1, 0.9, len(pos)), np.full(len(pos), 0.25)], axis=1)
    return {"pos": pos.astype(np.float32), "normals": normals.astype(np.float32),
            "uv": uv.astype(np.float32), "joints": joints, "weights": weights.astype(np.float32),
            "faces": np.asarray(faces, np.uint16)}


def make_glb(path: Path, *, skin: bool = True, interpolation: str = "LINEAR") -> Path:
    bar, chunks, views, accessors = _bar(), [], [], []

    def add(array: np.ndarray, component: int, kind: str, extra: dict | None = None) -> int:
        data = np.ascontiguousarray(array).tobytes()
        offset = sum(len(c) for c in chunks)
        chunks.append(data + b"\0" * (-len(data) % 4))
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data)})
        count = len(array) if kind != "SCALAR" else array.size
        accessors.append({"bufferView": len(views) - 1, "componentType": component,
                          "count": count, "type": kind, **(extra or {})})
        return len(accessors) - 1

    attrs = {"POSITION": add(bar["pos"], 5126, "VEC3"),
             "NORMAL": add(bar["normals"], 5126, "VEC3"),
             "TEXCOORD_0": add(bar["uv"], 5126, "VEC2"),
             "JOINTS_0": add(bar["joints"], 5121, "VEC4"),
             "WEIGHTS_0": add(bar["weights"], 5126, "VEC4")}
    indices = add(bar["faces"].reshape(-1), 5123, "SCALAR")
    # Inverse bind matrices (column-major): the root at the origin, the upper joint at y = 1.
    ibm = np.stack([np.eye(4), np.eye(4)]).astype(np.float32)
    ibm[1, 1, 3] = -1.0
    ibm_index = add(np.transpose(ibm, (0, 2, 1)).reshape(2, 16), 5126, "MAT4")
    times = np.array([0.0, 1.0], np.float32)
    half = math.sqrt(0.5)
    quats = np.array([[0, 0, 0, 1], [0, 0, half, half]], np.float32)  # 0 -> 90 deg about z
    if interpolation == "CUBICSPLINE":  # zero tangents around each value
        quats = np.stack([np.zeros_like(quats), quats, np.zeros_like(quats)], 1).reshape(-1, 4)
    anim = {"samplers": [{"input": add(times, 5126, "SCALAR"),
                          "output": add(quats, 5126, "VEC4"), "interpolation": interpolation}],
            "channels": [{"sampler": 0, "target": {"node": 2, "path": "rotation"}}]}
    png = io.BytesIO()
    Image.fromarray(TEXELS).save(png, format="PNG")
    image_data = png.getvalue()
    offset = sum(len(c) for c in chunks)
    chunks.append(image_data + b"\0" * (-len(image_data) % 4))
    views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(image_data)})
    mesh_node = {"mesh": 0, "skin": 0} if skin else {"mesh": 0}
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0, 1]}],
           "nodes": [mesh_node, {"children": [2]}, {"translation": [0, 1, 0]}],
           "meshes": [{"primitives": [{"attributes": attrs, "indices": indices,
                                       "material": 0}]}],
           "skins": [{"joints": [1, 2], "inverseBindMatrices": ibm_index}],
           "animations": [anim],
           "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
           "textures": [{"source": 0}],
           "images": [{"bufferView": len(views) - 1, "mimeType": "image/png"}],
           "accessors": accessors, "bufferViews": views,
           "buffers": [{"byteLength": sum(len(c) for c in chunks)}]}
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    binary = b"".join(chunks)
    body = (struct.pack("<II", len(text), 0x4E4F534A) + text
            + struct.pack("<II", len(binary), 0x004E4942) + binary)
    path.write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)
    return path


def _z_up(p: np.ndarray) -> np.ndarray:
    return np.stack([p[:, 0], -p[:, 2], p[:, 1]], axis=1)


def test_the_upper_bone_turns_and_the_lower_stays(tmp_path):
    c = GltfCharacter(make_glb(tmp_path / "bar.glb"))
    assert c.duration == 1.0 and c.rest.shape == (16, 3) and c.faces.shape == (24, 3)
    # +Z up; the bar is centred on the z axis with its foot at z = 0 already (no offset).
    np.testing.assert_allclose(c.pose(0.0).vertices, _z_up(c.rest), atol=1e-6)
    for t, angle in ((0.75, 67.5), (0.5, 45.0), (0.25, 22.5)):
        posed = c.pose(t).vertices
        a = math.radians(angle)
        R = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        pivot = np.array([0.0, 1.0, 0.0])
        want = c.rest.copy()
        upper = c.rest[:, 1] > 1.0
        want[upper] = (c.rest[upper] - pivot) @ R.T + pivot
        np.testing.assert_allclose(posed, _z_up(want), atol=1e-5, err_msg=f"t={t}")
        n = c.pose(t).normals
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
        n_want = _z_up(np.where(upper[:, None], c._normals @ R.T, c._normals))
        np.testing.assert_allclose(n, n_want, atol=1e-5)
    # The animation loops: t and t + duration are the same pose.
    np.testing.assert_allclose(c.pose(1.25).vertices, c.pose(0.25).vertices, atol=1e-9)
    assert c.height == pytest.approx(2.0)


def test_step_and_cubic_samplers(tmp_path):
    step = GltfCharacter(make_glb(tmp_path / "step.glb", interpolation="STEP"))
    np.testing.assert_allclose(step.pose(0.9).vertices, step.pose(0.0).vertices, atol=1e-9)
    cubic = GltfCharacter(make_glb(tmp_path / "cubic.glb", interpolation="CUBICSPLINE"))
    linear = GltfCharacter(make_glb(tmp_path / "linear.glb"))
    # Zero tangents: a smoothstep in the quaternion, the same pose at both ends and halfway.
    for t in (0.0, 0.5, 1.0):
        np.testing.assert_allclose(cubic.pose(t).vertices, linear.pose(t).vertices, atol=1e-5)
    assert not np.allclose(cubic.pose(0.2).vertices, linear.pose(0.2).vertices, atol=1e-4)


def test_texels_are_sampled_bilinearly_in_linear_albedo(tmp_path):
    c = GltfCharacter(make_glb(tmp_path / "bar.glb"))
    texture = c.textures[0]
    want = srgb_to_linear(TEXELS / 255.0) * ALBEDO_SCALE
    np.testing.assert_allclose(texture, want, atol=1e-9)
    centres = np.array([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]])
    np.testing.assert_allclose(sample_texture(texture, centres),
                               want.reshape(4, 3), atol=1e-9)
    mid = sample_texture(texture, np.array([[0.5, 0.25]]))[0]  # between red and green
    np.testing.assert_allclose(mid, (want[0, 0] + want[0, 1]) / 2, atol=1e-9)
    wrapped = sample_texture(texture, np.array([[1.25, -0.75]]))[0]  # repeats
    np.testing.assert_allclose(wrapped, want[0, 0], atol=1e-9)
    albedo = c.albedo(np.zeros(2, np.int64), centres[:2])
    np.testing.assert_allclose(albedo, want[0], atol=1e-9)


def test_files_that_are_not_skinned_characters_are_refused(tmp_path):
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"not a gltf file at all")
    with pytest.raises(ValueError, match="not a binary glTF"):
        GltfCharacter(bad)
    with pytest.raises(ValueError, match="no skinned mesh"):
        GltfCharacter(make_glb(tmp_path / "static.glb", skin=False))
    good = make_glb(tmp_path / "good.glb").read_bytes()
    (tmp_path / "cut.glb").write_bytes(good[: len(good) // 2])
    with pytest.raises(ValueError, match="truncated"):
        GltfCharacter(tmp_path / "cut.glb")
    with pytest.raises(ValueError, match="cannot read"):
        GltfCharacter(tmp_path / "missing.glb")


def test_dgs_synth_films_a_character(tmp_path):
    from core.cli import main
    from core.data import load_capture
    from core.plyio import read_mesh_ply

    glb = make_glb(tmp_path / "bar.glb")
    out = tmp_path / "capture"
    assert main(["synth", str(out), "--frames", "3", "--views", "4", "--size", "24", "24",
                 "--subject", str(glb), "--fps", "2"]) == 0
    capture = load_capture(out)
    assert capture.frames == ("000000", "000001", "000002")
    meshes = [read_mesh_ply(out / "gt" / "meshes" / f"{f}.ply") for f in capture.frames]
    assert all(len(m[0]) == 16 for m in meshes)  # one vertex per character vertex, every frame
    # Frame 1 is half a second in: the upper bone has turned 45 degrees.
    c = GltfCharacter(glb)
    np.testing.assert_allclose(meshes[1][0], c.pose(0.5).vertices, atol=1e-5)
    masks = [np.asarray(Image.open(out / "masks" / f / "cam00.png")) for f in capture.frames]
    assert masks[0].any() and not np.array_equal(masks[0], masks[1])  # frame 2 = 0 (looped)
    assert main(["synth", str(tmp_path / "other"), "--subject",
                 str(tmp_path / "missing.glb")]) == 2
    assert main(["synth", str(tmp_path / "other"), "--subject", str(glb), "--fps", "0"]) == 2
    assert not (tmp_path / "other").exists()  # refused before anything is written
