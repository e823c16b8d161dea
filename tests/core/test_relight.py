"""core.relight: SH9 irradiance against closed forms and quadrature, lights, the deferred shading
against the synthetic renderer's own model, tone mapping, camera paths, MP4, bad input, and a
tiny run relit end to end (CLI included)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from core.data.images import write_exr
from core.config.relight import Light
from core.relight import (
    equirect_directions,
    irradiance_sh9,
    load_capture_light,
    load_envmap,
    parse_light,
    project_sh9,
    relight_run,
    sh9_basis,
)
from core.relight.cameras import load_camera_path, orbit_cameras
from core.color import linear_to_srgb, srgb_to_linear
from core.relight.gbuffer import GBuffer
from core.relight.output import Mp4Writer, read_mp4_info
from core.relight.shade import light_irradiance, shade

pytestmark = pytest.mark.usefixtures("one_thread")

H, W = 64, 128
NORMALS = np.array([[0, 0, 1.0], [1, 0, 0], [0, -1, 0], [0.3, 0.5, 0.81], [-0.7, 0.1, -0.2]])
NORMALS /= np.linalg.norm(NORMALS, axis=1, keepdims=True)
# Midpoint quadrature of the 64x128 grid: about 1e-4 relative error on smooth maps.
QUAD_RTOL = 5e-4


def _map(fn, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    d, _ = equirect_directions(H, W, up)
    return np.repeat(fn(d)[..., None], 3, axis=-1).astype(np.float32)


def _brute_irradiance(radiance: np.ndarray, n: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    d, d_omega = equirect_directions(H, W, up)
    cos = np.maximum(d.reshape(-1, 3) @ n.T, 0.0)  # (P, N)
    return (radiance[..., 0].reshape(-1, 1) * cos * d_omega.reshape(-1, 1)).sum(0)


def test_constant_map_irradiance_is_pi_l():
    e = irradiance_sh9(NORMALS, project_sh9(np.full((H, W, 3), 0.7, np.float32)))
    np.testing.assert_allclose(e, math.pi * 0.7, rtol=QUAD_RTOL)


def test_linear_map_irradiance_closed_form():
    # L(w) = 1 + w.z is band-limited (l <= 1): E(n) = pi + (2 pi / 3) n.z exactly
    # (Ramamoorthi & Hanrahan 2001, eq. 8: A_0 = pi, A_1 = 2 pi / 3).
    e = irradiance_sh9(NORMALS, project_sh9(_map(lambda d: 1 + d[..., 2])))
    np.testing.assert_allclose(e[:, 0], math.pi + 2 * math.pi / 3 * NORMALS[:, 2], rtol=QUAD_RTOL)


def test_band_limited_map_matches_quadrature_of_the_clamped_cosine():
    radiance = _map(lambda d: 1 + 0.5 * d[..., 0] * d[..., 1] + 0.3 * d[..., 1]
                    + 0.2 * (3 * d[..., 2] ** 2 - 1))
    e = irradiance_sh9(NORMALS, project_sh9(radiance))[:, 0]
    np.testing.assert_allclose(e, _brute_irradiance(radiance, NORMALS), rtol=1e-3)


def test_rotation_about_up_and_a_non_z_up_axis():
    # A map brighter towards +x, turned 90 degrees about +z, is brighter towards +y.
    radiance = _map(lambda d: 1 + d[..., 0])
    e = irradiance_sh9(np.array([[0, 1.0, 0], [1.0, 0, 0]]), project_sh9(radiance,
                                                                         rotation_deg=90))
    np.testing.assert_allclose(e[:, 0], [math.pi + 2 * math.pi / 3, math.pi], rtol=QUAD_RTOL)
    # With up = -y (the OpenCV-style capture default), row 0 of the map is the -y pole.
    up = (0.0, -1.0, 0.0)
    top = np.zeros((H, W, 3), np.float32)
    top[: H // 8] = 1.0
    e = irradiance_sh9(np.array([[0, -1.0, 0], [0, 1.0, 0]]), project_sh9(top, up))
    assert e[0, 0] > 10 * e[1, 0]


def test_basis_matches_the_synthetic_renderer_and_torch():
    from core.synth.shading import sh9_basis as synth_basis

    d, _ = equirect_directions(8, 16)
    d = d.reshape(-1, 3)
    np.testing.assert_allclose(sh9_basis(d), synth_basis(d), atol=2e-6)  # its constants: 6 digits
    np.testing.assert_allclose(sh9_basis(torch.from_numpy(d)).numpy(), sh9_basis(d), atol=1e-12)


def test_synth_envmap_file_round_trips_to_its_coefficients(synth_capture: Path):
    lights = json.loads((synth_capture / "gt" / "lights.json").read_text())
    for name, light in lights["lights"].items():
        env = load_envmap(synth_capture / "gt" / light["envmap"])
        ref = np.asarray(light["sh9_radiance"])
        n = NORMALS
        # The file stores the SH9 radiance clamped at 0 on a 32x64 grid: the irradiance it gives
        # is within a few percent of the coefficients'.
        e_file, e_ref = irradiance_sh9(n, env.sh9), irradiance_sh9(n, ref)
        assert np.abs(e_file - e_ref).max() < 0.05 * e_ref.max(), name


def test_lights_irradiance():
    n = torch.tensor([[[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]])
    pts = torch.zeros(1, 2, 3)
    sun = Light(kind="directional", direction=(0.0, 0.0, 5.0), intensity=math.pi,
                color=(1.0, 0.5, 0.0))
    e = light_irradiance(n, pts, [sun])
    np.testing.assert_allclose(e[0, 0].numpy(), [math.pi, math.pi / 2, 0.0], rtol=1e-6)
    assert e[0, 1].abs().max() == 0  # perpendicular: no light
    lamp = Light(kind="point", position=(0.0, 0.0, 2.0), intensity=8.0)
    e = light_irradiance(n, pts, [lamp])
    np.testing.assert_allclose(e[0, 0].numpy(), [2.0] * 3, rtol=1e-6)  # 8 / 2^2
    both = light_irradiance(n, pts, [sun, lamp])
    np.testing.assert_allclose(both.numpy(), (light_irradiance(n, pts, [sun])
                                              + light_irradiance(n, pts, [lamp])).numpy())
    assert parse_light("point:0,0,2:8") == lamp
    assert parse_light("directional:0,0,5:3.14:1,0.5,0").color == (1.0, 0.5, 0.0)
    assert Light.model_validate(lamp.model_dump(mode="json")) == lamp


def _gbuffer(n: int = 256, seed: int = 0, capture_sh9=None):
    """A random G-buffer whose base colour follows the synthetic model under `capture_sh9`."""
    g = torch.Generator().manual_seed(seed)
    normal = torch.nn.functional.normalize(torch.randn(1, n, 3, generator=g), dim=-1)
    albedo = 0.1 + 0.8 * torch.rand(1, n, 3, generator=g)
    vis = 0.3 + 0.7 * torch.rand(1, n, 1, generator=g)
    e_cap = irradiance_sh9(normal.double(), torch.as_tensor(capture_sh9)).float()
    gb = GBuffer(base=albedo * vis * e_cap, residual=torch.zeros(1, n, 3), normal=normal,
                 visibility=vis, depth=torch.ones(1, n, 1), alpha=torch.ones(1, n, 1),
                 alpha_g=torch.ones(1, n, 1), points=torch.zeros(1, n, 3))
    return gb, albedo, vis


def test_shading_inverts_the_capture_light_and_applies_the_new_one():
    """Reference: the synthetic renderer's model, linear = albedo * visibility * E(n)."""
    from core.synth.shading import LIGHTS

    cap, new = LIGHTS["capture"].sh9(), LIGHTS["relight"].sh9()
    gb, albedo, vis = _gbuffer(capture_sh9=cap)
    # Keep normals the capture light lit well (the albedo of a dark side is floored).
    e_cap = irradiance_sh9(gb.normal.double(), torch.as_tensor(cap))
    lit = (e_cap.min(-1).values > 0.2 * float(e_cap.mean()))[0]
    light = load_capture_light(None)
    light = type(light)(None, cap, "test")
    out = shade(gb, new, light)
    expect = albedo * vis * irradiance_sh9(gb.normal.double(), torch.as_tensor(new)).float()
    torch.testing.assert_close(out.linear[0, lit], expect[0, lit], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out.albedo[0, lit], albedo[0, lit], rtol=1e-4, atol=1e-5)
    # Without the AO term the shading multiplies by 1 instead of the visibility.
    no_ao = shade(gb, new, light, ao=False)
    torch.testing.assert_close(no_ao.linear[0, lit], (expect / vis)[0, lit], rtol=1e-4,
                               atol=1e-5)
    # A uniform capture light of pi under a unit-radiance map gives the base colour back.
    flat = project_sh9(np.ones((H, W, 3), np.float32))
    gb.base = albedo * vis
    same = shade(gb, flat, load_capture_light(None))
    torch.testing.assert_close(same.linear, gb.base, rtol=1e-3, atol=1e-5)
    # The view-dependent residual is added as is.
    gb.residual = torch.full_like(gb.base, 0.05)
    torch.testing.assert_close(shade(gb, flat, load_capture_light(None)).linear,
                               gb.base + 0.05, rtol=1e-3, atol=1e-5)


def test_srgb_transfer():
    x = torch.tensor([0.0, 0.0031308, 0.5, 1.0, 2.0])
    # IEC 61966-2-1: 0.5 linear is 0.735357 encoded; values above 1 clip (the tone map).
    np.testing.assert_allclose(linear_to_srgb(x).numpy(), [0, 0.04045, 0.735357, 1, 1],
                               atol=2e-5)
    y = torch.linspace(0, 1, 101)
    torch.testing.assert_close(linear_to_srgb(srgb_to_linear(y)), y, atol=1e-5, rtol=0)


def test_hdr_reads_as_rgb(tmp_path: Path):
    import cv2

    rgb = np.zeros((8, 16, 3), np.float32)
    rgb[..., 0] = 4.0  # red, above 1
    rgb[..., 2] = 0.25
    assert cv2.imwrite(str(tmp_path / "map.hdr"), rgb[..., ::-1].copy())  # OpenCV writes BGR
    env = load_envmap(tmp_path / "map.hdr", exposure=1.0)
    np.testing.assert_allclose(env.radiance[0, 0], [8.0, 0.0, 0.5], rtol=0.02)  # RGBE: 1%


def _write(tmp_path: Path, name: str, image: np.ndarray) -> Path:
    path = tmp_path / name
    write_exr(path, image)
    return path


def test_bad_environment_maps(tmp_path: Path):
    good = np.ones((8, 16, 3), np.float32)
    cases = {
        "not found": (tmp_path / "missing.exr", "not found"),
        "garbage exr": (tmp_path / "junk.exr", "corrupt OpenEXR header"),
        "garbage hdr": (tmp_path / "junk.hdr", "truncated Radiance HDR header"),
        "png": (tmp_path / "map.png", "unsupported file type"),
        "square": (_write(tmp_path, "sq.exr", np.ones((8, 8, 3), np.float32)),
                   "twice as wide"),
        "nan": (_write(tmp_path, "nan.exr", np.where(np.arange(16)[:, None] == 3, np.nan, good)),
                "NaN or Inf"),
        "inf": (_write(tmp_path, "inf.exr", np.where(np.arange(16)[:, None] == 5, np.inf, good)),
                "NaN or Inf"),
        "negative": (_write(tmp_path, "neg.exr", -good), "negative"),
        "black": (_write(tmp_path, "black.exr", 0 * good), "every pixel is zero"),
    }
    (tmp_path / "junk.exr").write_bytes(b"\x76\x2f\x31\x01garbage" * 10)
    (tmp_path / "junk.hdr").write_bytes(b"#?RADIANCE\nnonsense")
    (tmp_path / "map.png").write_bytes(b"x")
    for name, (path, message) in cases.items():
        with pytest.raises(ValueError, match=message):
            load_envmap(path)
        assert str(path) in str(pytest.raises(ValueError, load_envmap, path).value), name
    with pytest.raises(ValueError, match="exposure"):
        load_envmap(_write(tmp_path, "ok.exr", good), exposure=float("nan"))


def test_a_map_ringing_slightly_below_zero_is_clamped(tmp_path: Path):
    """Resampled HDRIs (Poly Haven's) dip to about -2e-3 beside bright lights: loaded as 0."""
    from core.relight.envmap import check_radiance

    ring = np.ones((8, 16, 3), np.float32)
    ring[2, 3, 1] = -2e-3
    clamped = check_radiance(ring, "ring.exr")
    assert clamped.min() == 0.0 and clamped[2, 3, 1] == 0.0 and clamped[0, 0, 0] == 1.0
    ring[2, 3, 1] = -0.05  # 5% of the mean: not ringing
    with pytest.raises(ValueError, match="1 pixel"):
        check_radiance(ring, "ring.exr")


@pytest.mark.parametrize("spec, message", [
    ("directional:0,0,1:0", "needs an intensity > 0"),
    ("point:0,0,1:-2", "needs an intensity > 0"),
    ("directional:0,0,0:1", "direction must not be zero"),
    ("directional:0,0,1:nan", "intensity"),
    ("directional:0,0,1:1:0,0,0", "must not be all zero"),
    ("spot:0,0,1:1", "expected directional"),
    ("point:0,0:1", "3 finite numbers"),
])
def test_bad_lights(spec: str, message: str):
    with pytest.raises(ValueError, match=message):
        parse_light(spec)


def test_bad_light_json():
    with pytest.raises(ValueError, match="intensity > 0"):
        Light.model_validate({"kind": "directional", "direction": [0, 0, 1], "intensity": 0})
    with pytest.raises(ValueError, match="needs 'position'"):
        Light.model_validate({"kind": "point", "intensity": 1})


def test_camera_path_round_trip_and_errors(tmp_path: Path, synth_capture: Path):
    from core.data import load_capture

    cam = load_capture(synth_capture).cameras[1]
    c2w_gl = cam.camera_to_world @ np.diag([1.0, -1, -1, 1])
    fov = math.degrees(2 * math.atan(cam.height / 2 / cam.K[1, 1]))
    doc = {"render_width": cam.width, "render_height": cam.height, "fps": 12,
           "camera_path": [{"camera_to_world": c2w_gl.ravel().tolist(), "fov": fov,
                            "aspect": cam.width / cam.height}]}
    path = tmp_path / "camera_path.json"
    path.write_text(json.dumps(doc))
    cams, fps = load_camera_path(path)
    assert fps == 12 and len(cams) == 1
    np.testing.assert_allclose(cams[0].world_to_camera, cam.world_to_camera, atol=1e-9)
    np.testing.assert_allclose(cams[0].K[1, 1], cam.K[1, 1], rtol=1e-9)
    for broken, message in [({**doc, "camera_path": []}, "empty"),
                            ({"frames": []}, "no 'camera_path'"),
                            ({**doc, "camera_path": [{"camera_to_world": [1] * 15, "fov": 50}]},
                             "16 numbers"),
                            ({**doc, "camera_path": [{**doc["camera_path"][0], "fov": 0}]},
                             "fov")]:
        path.write_text(json.dumps(broken))
        with pytest.raises(ValueError, match=message):
            load_camera_path(path)


def test_orbit_looks_at_the_centre(synth_capture: Path):
    from core.data import load_capture

    capture = load_capture(synth_capture)
    center = np.array([0.0, 0.0, 0.9])
    cams = orbit_cameras(capture.cameras, center, capture.up, 6)
    assert [c.id for c in cams] == [f"orbit{i:03d}" for i in range(6)]
    dist = np.mean([np.linalg.norm(c.center - center) for c in capture.cameras])
    for c in cams:
        uv, z = c.project(center[None])
        np.testing.assert_allclose(uv[0], [c.K[0, 2], c.K[1, 2]], atol=1e-6)
        assert z[0] == pytest.approx(dist)
    with pytest.raises(ValueError, match="orbit"):
        orbit_cameras(capture.cameras, center, capture.up, 0)


def test_mp4_writer_pads_odd_sizes(tmp_path: Path):
    with Mp4Writer(tmp_path / "v.mp4", 17, 11, fps=10) as w:
        for i in range(3):
            w.write(np.full((11, 17, 3), 40 * i, np.uint8))
    info = read_mp4_info(tmp_path / "v.mp4")
    assert (info["frames"], info["width"], info["height"]) == (3, 18, 12)
    assert "h264" in info["codec"] and "yuv420p" in info["pix_fmt"]
