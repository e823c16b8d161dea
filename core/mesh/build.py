"""A watertight mesh of one reconstructed frame (docs/design.md section 5, Mesh): TSDF fusion of the
geometry branch's expected depth where alpha_g > 0.5 over the training cameras, voxel = scene
diagonal / 512, truncation 5 voxels, marching cubes, the largest components kept.

Vertex colours are render-and-project: each vertex takes the cosine-weighted mean of the
appearance render (full SH, straight colour) of every training camera that sees it (its depth
within a tolerance of the camera's geometry depth); a vertex no camera sees takes the base colour
of its nearest opaque Gaussian.

`depth="appearance"` is the baseline that meshes the appearance branch's depth instead: both
opacities of every Gaussian are set to its appearance opacity as the final render mixes it,
o_c = ((1 + beta) opacity_c + (1 - beta) opacity_g) / 2 (docs/design.md 3.4), and the model is
rendered at beta 0, so the rasterizer's (geometry-weighted) depth and coverage are exactly the
appearance branch's alpha_c-weighted ones.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from core.color import linear_to_srgb
from core.config import MeshConfig
from core.data.layout import common_radius, look_at_center
from core.mesh.surface import clean_mesh, extract_surface
from core.mesh.tsdf import TSDFVolume
from core.model import SH_C0, GaussianModel
from core.render import render, safe_divide

__all__ = ["appearance_model", "mesh_model", "scene_box"]


def appearance_model(model, beta: float):
    """A copy of `model` whose two opacities both equal the appearance opacity the final render
    uses at `beta` (render it at beta 0)."""
    with torch.no_grad():
        o = 0.5 * ((1 + beta) * model.opacity_c + (1 - beta) * model.opacity_g)
        logit = torch.logit(o.clamp(1e-6, 1 - 1e-6))
        params = {k: v.detach() for k, v in model.params.items()}
        params["opacity_c"] = params["opacity_g"] = logit
        return GaussianModel(params)


def scene_box(model, cameras, mode: str = "gaussians") -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the scene, unpadded (see MeshConfig.box)."""
    if mode == "cameras":
        c = look_at_center(cameras)
        r = common_radius(cameras, c)
        return c - r, c + r
    with torch.no_grad():
        opaque = torch.maximum(model.opacity_c, model.opacity_g) > 0.5
        pts = (model.means[opaque] if int(opaque.sum()) >= 4
               else model.means).double().cpu().numpy()
    if len(pts) == 0:
        raise ValueError("model: has no Gaussians to take a scene box from")
    lo, hi = np.percentile(pts, 0.5, axis=0), np.percentile(pts, 99.5, axis=0)
    return lo, np.maximum(hi, lo + 1e-3)


@torch.no_grad()
def _render(model, cam, settings, beta: float):
    """One view rendered where the model lives (the GPU when it is there)."""
    dev = model.device
    return render(model, settings.camera(cam, device=dev), sh_degree=settings.sh_degree,
                  beta=beta, geometry=True, background=torch.zeros(3, device=dev),
                  eps2d=settings.eps2d, antialiased=settings.antialiased)


def _fuse(model, cameras, settings, config: MeshConfig, lo, hi, voxel, device) -> TSDFVolume:
    src, beta = (model, settings.beta) if config.depth == "geometry" else (
        appearance_model(model, settings.beta), 0.0)
    vol = TSDFVolume.create(lo, hi, voxel, config.truncation_voxels, device=device,
                            chunk=config.chunk)
    depths, Ks, views = [], [], []
    for cam in cameras:
        r = _render(src, cam, settings, beta)
        ok = (r.alpha_g[..., 0] > config.alpha_threshold) & (r.depth[..., 0] > 0)
        depths.append(torch.where(ok, r.depth[..., 0], 0.0))
        Ks.append(torch.from_numpy(np.asarray(cam.K, np.float32)))
        views.append(torch.from_numpy(np.asarray(cam.world_to_camera, np.float32)))
    vol.integrate(depths, Ks, views)
    return vol


def _project(cam, pts: Tensor) -> tuple[Tensor, Tensor]:
    """`core.data.Camera.project` of (N, 3) points on their device: pixels (N, 2), depth."""
    R = torch.as_tensor(np.asarray(cam.R), dtype=pts.dtype, device=pts.device)
    t = torch.as_tensor(np.asarray(cam.t), dtype=pts.dtype, device=pts.device)
    c = pts @ R.T + t
    z = c[:, 2]
    return torch.stack(cam.pixels(c[:, 0] / z, c[:, 1] / z), 1), z


@torch.no_grad()
def vertex_colors(mesh, model, cameras, settings, *, voxel: float, alpha_threshold: float,
                  linear_capture: bool) -> np.ndarray:
    """(V, 4) uint8 sRGB colours (see module doc), computed where the model lives."""
    dev = model.device
    verts_np = np.asarray(mesh.vertices, np.float64)
    verts = torch.from_numpy(verts_np).to(dev)
    normals = torch.from_numpy(np.array(mesh.vertex_normals, np.float64)).to(dev)
    acc = torch.zeros(len(verts), 3, dtype=torch.float64, device=dev)
    wsum = torch.zeros(len(verts), dtype=torch.float64, device=dev)
    for cam in cameras:
        r = _render(model, cam, settings, settings.beta)
        rgb = safe_divide(r.rgb, r.alpha_c).clamp(0, 1).double()
        depth, cover = r.depth[..., 0].double(), r.alpha_g[..., 0].double()
        uv, z = _project(cam, verts)
        u, v = torch.floor(uv[:, 0]), torch.floor(uv[:, 1])
        ok = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        uc = u.nan_to_num(0).clamp(0, cam.width - 1).long()
        vc = v.nan_to_num(0).clamp(0, cam.height - 1).long()
        tol = (0.01 * z).clamp_min(3 * voxel)
        ok &= (cover[vc, uc] > alpha_threshold) & ((depth[vc, uc] - z).abs() < tol)
        to_cam = torch.as_tensor(np.asarray(cam.center), device=dev)[None] - verts
        w = ((normals * to_cam).sum(1) / to_cam.norm(dim=1)).clamp(0, 1) * ok
        acc += rgb[vc, uc] * w[:, None]
        wsum += w
    acc, wsum, verts = acc.cpu().numpy(), wsum.cpu().numpy(), verts_np
    colors = acc / np.maximum(wsum, 1e-12)[:, None]
    unseen = wsum <= 1e-6
    if unseen.any():
        keep = model.opacity_c > 0.5
        means = (model.means[keep] if int(keep.sum()) else model.means).double().cpu().numpy()
        base = ((model.params["sh0"][:, 0] * SH_C0 + 0.5).clamp(0, 1)[keep] if int(keep.sum())
                else (model.params["sh0"][:, 0] * SH_C0 + 0.5).clamp(0, 1)).cpu().numpy()
        colors[unseen] = base[cKDTree(means).query(verts[unseen])[1]]
    if linear_capture:
        colors = linear_to_srgb(colors)
    rgba = np.concatenate([colors, np.ones((len(verts), 1))], axis=1)
    return (np.clip(rgba, 0, 1) * 255 + 0.5).astype(np.uint8)


def mesh_model(model, cameras, settings, config: MeshConfig = MeshConfig(), *,
               linear_capture: bool = False, up=None):
    """(trimesh.Trimesh in the model's world coordinates, info dict) of one frame's model seen
    by the training `cameras` (core.data.Camera at the run's resolution); with the capture's
    `up` an unseen bottom is closed at the lowest observed surface (`TSDFVolume.values`)."""
    if not cameras:
        raise ValueError("cameras: expected at least one training camera")
    device = config.device or ("cuda" if torch.cuda.is_available() else "cpu")
    t0 = time.perf_counter()
    lo, hi = scene_box(model, cameras, config.box)
    diag = float(np.linalg.norm(hi - lo))
    voxel = diag / config.resolution
    pad = config.margin * diag + (config.truncation_voxels + 2) * voxel
    vol = _fuse(model, cameras, settings, config, lo - pad, hi + pad, voxel, device)
    t1 = time.perf_counter()
    mesh = clean_mesh(extract_surface(vol.values(up), vol.lo, voxel), config.min_component)
    t2 = time.perf_counter()
    if config.colors:
        mesh.visual.vertex_colors = vertex_colors(
            mesh, model, cameras, settings, voxel=voxel, alpha_threshold=config.alpha_threshold,
            linear_capture=linear_capture)
    info = {"voxel": voxel, "grid": list(vol.shape), "scene_diagonal": diag,
            "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
            "watertight": bool(mesh.is_watertight), "depth": config.depth, "device": str(device),
            "seconds": {"fusion": round(t1 - t0, 3), "surface": round(t2 - t1, 3),
                        "colors": round(time.perf_counter() - t2, 3)}}
    info["seconds"]["total"] = round(math.fsum(info["seconds"].values()), 3)
    return mesh, info
