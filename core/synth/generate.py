"""`dgs synth`: a synthetic multi-view sequence of the articulated figure, with ground truth.

Layout written (capture content per docs/design.md 3.1, ground truth beside it under ``gt/``)::

    OUT/capture.json
    OUT/images/<frame>/<cam>.png           sRGB 8-bit, straight colour (see below), black background
    OUT/masks/<frame>/<cam>.png            coverage 0..1 as 8-bit (fraction of the pixel on the figure)
    OUT/normals/<frame>/<cam>.png          only with priors: degraded world normals, (n + 1) / 2
    OUT/gt/meshes/<frame>.ply              posed mesh, world coordinates
    OUT/gt/depth/<frame>/<cam>.npy         (H, W) float32 camera z, 0 on background
    OUT/gt/normals/<frame>/<cam>.npy       (H, W, 3) float32 unit world normals, 0 on background
    OUT/gt/albedo/<frame>/<cam>.png        albedo, sRGB 8-bit
    OUT/gt/visibility/<frame>/<cam>.png    ambient visibility 0..1, linear 8-bit
    OUT/gt/relight/<frame>/<cam>.png       the same view under the second light
    OUT/gt/lights.json, OUT/gt/envmaps/<light>.exr

Pixels integrate over their area, as a sensor does: every view is rendered at k x k samples per
pixel (`SynthConfig.supersample`). The mask stores coverage (the fraction of samples on the
figure) and the images store *straight* (unpremultiplied) colour, the mean of the stored (sRGB)
values over the figure's samples, so that ``image * mask + bg * (1 - mask)`` is exactly the area
average of the pixel in front of any background ``bg`` (the convention of core.data.dataset; PNG
alpha is straight too). Albedo, visibility and relight images follow the same convention with the
same mask. Geometric ground truth (depth, normals, the support of the priors) stays point-sampled
at the pixel centres, which an odd k includes exactly.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from core.color import linear_to_srgb
from core.data.capture import Camera, Capture, save_capture
from core.data.images import write_exr, write_png
from core.plyio import write_mesh_ply
from core.synth.figure import Figure, FigureMesh
from core.synth.gltf import GltfCharacter
from core.synth.raster import interpolate, rasterize_perspective
from core.synth.shading import (
    LIGHTS,
    albedo_at,
    irradiance,
    sh9_basis,
    vertex_visibility,
)

__all__ = ["SynthConfig", "dome_cameras", "look_at", "synthesize"]

_TARGET = np.array([0.0, 0.0, 0.9])
_UP = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class SynthConfig:
    """What to generate."""

    frames: int = 3
    """Number of frames (the figure moves between them)."""
    views: int = 16
    """Number of cameras on the dome."""
    width: int = 128
    """Image width in pixels."""
    height: int = 128
    """Image height in pixels."""
    seed: int = 0
    """Seeds colours, motion phases, camera jitter and prior noise; same seed, same bytes."""
    priors: bool = False
    """Also write normals/ with stand-in monocular normal priors."""
    ao_directions: int = 64
    """Directions used for the ambient-occlusion shadow maps."""
    radius: float = 3.2
    """Camera distance from the figure's centre (metres)."""
    supersample: int = 3
    """Odd k: k x k samples per pixel for images and coverage masks (1: one sample at the pixel
    centre, aliased edges and texture, binary masks)."""
    subject: str = ""
    """What is filmed: "" the articulated figure; a path to a skinned, animated glTF 2.0
    character (.glb, `core.synth.gltf`), textured by its base-colour map."""
    fps: float = 24.0
    """Frames per second of a glTF subject's animation (frame i is at i / fps seconds)."""

    def check(self) -> None:
        if self.supersample < 1 or self.supersample % 2 == 0:
            raise ValueError(f"supersample: expected an odd integer >= 1, got {self.supersample}")
        if not self.fps > 0:
            raise ValueError(f"fps: expected > 0, got {self.fps}")
        if self.subject and not Path(self.subject).is_file():
            raise ValueError(f"subject: {self.subject} is not a file (expected a .glb)")
        for name in ("frames", "views", "width", "height", "ao_directions"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")
        if self.width < 8 or self.height < 8:
            raise ValueError(f"size: expected at least 8x8, got {self.width}x{self.height}")


def look_at(eye, target, up) -> np.ndarray:
    """(4, 4) world-to-camera of a camera at `eye` looking at `target`, OpenCV axes (x right,
    y down, z forward), with `up` pointing up in the image."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([right, down, fwd])
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    return w2c


def dome_cameras(config: SynthConfig, rng: np.random.Generator) -> list[Camera]:
    """Cameras on the upper hemisphere (5..65 degrees elevation, golden-angle azimuths), looking at
    the figure, with a few percent of focal and principal-point jitter so intrinsics differ."""
    n, W, H = config.views, config.width, config.height
    s_lo, s_hi = np.sin(np.radians(5)), np.sin(np.radians(65))
    digits = max(2, len(str(n - 1)))
    az0 = rng.uniform(0, 2 * np.pi)
    cams = []
    for i in range(n):
        elev = np.arcsin(s_lo + (s_hi - s_lo) * (i + 0.5) / n)  # uniform in area over the band
        az = az0 + i * np.pi * (3 - np.sqrt(5))
        eye = _TARGET + config.radius * np.array(
            [np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)]
        )
        w2c = look_at(eye, _TARGET, _UP)
        # 36 degrees vertical field of view fits the 1.9 m figure with its swinging limbs.
        f = 0.5 * H / np.tan(np.radians(18)) * (1 + rng.uniform(-0.03, 0.03))
        cx = W / 2 * (1 + rng.uniform(-0.02, 0.02))
        cy = H / 2 * (1 + rng.uniform(-0.02, 0.02))
        K = np.array([[f, 0, cx], [0, f * (1 + rng.uniform(-0.01, 0.01)), cy], [0, 0, 1.0]])
        cams.append(Camera(f"cam{i:0{digits}d}", W, H, K, w2c, None))
    return cams


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x * 255.0), 0, 255).astype(np.uint8)


def _render_view(
    mesh: FigureMesh, vis: np.ndarray, cam: Camera, albedo_of, supersample: int = 1
) -> dict[str, np.ndarray]:
    """Point samples at the pixel centres ("mask", "depth", "normal"), coverage ("coverage") and
    straight stored-value colour ("albedo", "visibility" and one image per light, encoded as
    they are written: sRGB for colours, linear for visibility). `albedo_of(frags, mesh, part)`
    gives the linear albedo (M, 3) of the covered samples (`part` (M,): their mesh part)."""
    k, W, H = supersample, cam.width, cam.height
    # Continuous pixel coordinates scale by k, so the centre (u + 0.5) of pixel u is the centre of
    # sub-pixel k u + k // 2 when k is odd.
    K = np.diag([k, k, 1.0]) @ cam.K
    frags = rasterize_perspective(mesh.vertices, mesh.faces, K, cam.world_to_camera, W * k, H * k)
    m = frags.mask
    normals = interpolate(frags, mesh.faces, mesh.normals)
    normals[m] /= np.linalg.norm(normals[m], axis=1, keepdims=True)
    visibility = interpolate(frags, mesh.faces, vis[:, None])
    albedo = np.zeros_like(normals)
    albedo[m] = albedo_of(frags, mesh, mesh.part[mesh.faces[frags.triangle[m], 0]])
    stored = {"albedo": linear_to_srgb(albedo), "visibility": visibility}
    for name, light in LIGHTS.items():
        rgb = np.zeros_like(normals)
        rgb[m] = albedo[m] * visibility[m] * irradiance(normals[m], light.sh9())
        stored[name] = linear_to_srgb(rgb)
    c = k // 2
    blocks = lambda a: a.reshape(H, k, W, k, -1)  # noqa: E731  (pixel, sub-row, sub-column)
    count = blocks(m.astype(np.float64)).sum(axis=(1, 3))  # (H, W, 1) figure samples per pixel
    out = {
        "mask": m[c::k, c::k],
        "depth": frags.depth[c::k, c::k],
        "normal": normals[c::k, c::k],
        "coverage": count[..., 0] / (k * k),
    }
    for name, value in stored.items():
        mean = blocks(value * m[..., None]).sum(axis=(1, 3)) / np.maximum(count, 1)
        out[name] = mean[..., 0] if name == "visibility" else mean
    return out


def degrade_normals(normal: np.ndarray, mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Stand-in monocular prior: blur (edge-aware to the mask), a per-view tilt bias, noise."""
    m = mask.astype(np.float32)
    sigma = 1.2
    blurred = cv2.GaussianBlur((normal * m[:, :, None]).astype(np.float32), (0, 0), sigma)
    weight = cv2.GaussianBlur(m, (0, 0), sigma)[:, :, None]
    n = blurred / np.maximum(weight, 1e-6)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(3.0, 8.0))  # a real estimator is consistently off per view
    kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx
    n = n @ R.T + rng.normal(scale=0.06, size=n.shape)
    n /= np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-6)
    return np.where(mask[:, :, None], n, 0.0)


def _write_lights(gt: Path) -> None:
    envs = {}
    h, w = 32, 64
    theta = (np.arange(h) + 0.5) / h * np.pi
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    t, p = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=2).reshape(
        -1, 3
    )
    for name, light in LIGHTS.items():
        radiance = np.maximum(sh9_basis(dirs) @ light.sh9(), 0.0).reshape(h, w, 3)
        write_exr(gt / "envmaps" / f"{name}.exr", radiance)
        envs[name] = {**light.to_json(), "envmap": f"envmaps/{name}.exr"}
    doc = {
        "shading": "linear_rgb = albedo * visibility * E(n); images store sRGB(linear_rgb), 8-bit",
        "irradiance": "E(n) = max(0, sum_k A_k L_k Y_k(n)), A = (pi, 2pi/3 x3, pi/4 x5)",
        "sh_basis": "real SH: Y00, Y1-1 (y), Y10 (z), Y11 (x), Y2-2, Y2-1, Y20, Y21, Y22",
        "frame": "world coordinates, up = +z",
        "envmap_layout": "equirectangular radiance of the SH9 coefficients (clamped at 0); row r: "
        "polar angle pi (r + 0.5) / H from +z; column c: azimuth 2 pi (c + 0.5) / W from +x to +y",
        "lights": envs,
        "images": "capture",
        "relight": "relight",
    }
    (gt / "lights.json").write_text(json.dumps(doc, indent=1))


def synthesize(out: str | os.PathLike[str], config: SynthConfig = SynthConfig()) -> Capture:
    """Generate the capture and its ground truth into ``out`` (new or empty folder)."""
    config.check()
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"out: {out} exists and is not an empty folder")
    rng = np.random.default_rng(config.seed)
    figure = Figure(seed=int(rng.integers(2**31)))
    palette = rng.uniform(0.25, 0.85, size=(figure.n_parts, 3))
    pose, albedo_of = _subject(config, figure, palette)
    cameras = dome_cameras(config, rng)
    prior_rng = np.random.default_rng(rng.integers(2**31))
    frames = [f"{i:06d}" for i in range(config.frames)]
    gt = out / "gt"
    for i, frame in enumerate(frames):
        mesh = pose(i)
        vis = vertex_visibility(mesh.vertices, mesh.normals, mesh.faces, config.ao_directions)
        write_mesh_ply(gt / "meshes" / f"{frame}.ply", mesh.vertices, mesh.faces, mesh.normals)
        for cam in cameras:
            _write_view(
                out,
                frame,
                cam,
                _render_view(mesh, vis, cam, albedo_of, config.supersample),
                prior_rng if config.priors else None,
            )
    _write_lights(gt)
    record = {"generator": "dgs synth", "config": asdict(config), "ground_truth": "gt/"}
    capture = Capture(out, tuple(cameras), tuple(frames), _UP, extra={"synth": record})
    save_capture(capture)
    return capture


def _subject(config: SynthConfig, figure: Figure, palette: np.ndarray):
    """(pose(frame index) -> FigureMesh, albedo_of(frags, mesh, part) -> (M, 3)) of the
    subject (`_render_view`)."""
    if not config.subject:
        def figure_albedo(frags, mesh: FigureMesh, part: np.ndarray) -> np.ndarray:
            return albedo_at(interpolate(frags, mesh.faces, mesh.rest)[frags.mask], part, palette)

        return (lambda i: figure.pose(float(i))), figure_albedo

    character = GltfCharacter(config.subject)

    def texture_albedo(frags, mesh: FigureMesh, part: np.ndarray) -> np.ndarray:
        return character.albedo(part, interpolate(frags, mesh.faces, character.uv)[frags.mask])

    return (lambda i: character.pose(i / config.fps)), texture_albedo


def _write_view(out: Path, frame: str, cam: Camera, r: dict[str, np.ndarray], prior_rng) -> None:
    name = f"{frame}/{cam.id}"
    write_png(out / "images" / f"{name}.png", _to_u8(r["capture"]))
    write_png(out / "masks" / f"{name}.png", _to_u8(r["coverage"]))
    gt = out / "gt"
    for sub in ("depth", "normals"):
        (gt / sub / frame).mkdir(parents=True, exist_ok=True)
    np.save(gt / "depth" / f"{name}.npy", r["depth"].astype(np.float32))
    np.save(gt / "normals" / f"{name}.npy", r["normal"].astype(np.float32))
    write_png(gt / "relight" / f"{name}.png", _to_u8(r["relight"]))
    write_png(gt / "albedo" / f"{name}.png", _to_u8(r["albedo"]))
    write_png(gt / "visibility" / f"{name}.png", _to_u8(r["visibility"]))
    if prior_rng is not None:
        prior = degrade_normals(r["normal"], r["mask"], prior_rng)
        write_png(out / "normals" / f"{name}.png", _to_u8((prior + 1) / 2))
