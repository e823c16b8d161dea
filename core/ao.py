"""Ambient occlusion baking (docs/design.md section 5, "Ambient occlusion").

At the bake step of stage 3: every Gaussian's visibility attribute is initialised by tracing
rays over the hemisphere about its normal, and every training view gets a per-pixel AO map: the
geometry branch is rendered at 1/4 resolution, the covered pixels are back-projected to surface
points and traced about their rendered normals, and the map is upsampled and joint-bilateral
filtered (OpenCV contrib, ximgproc) guided by the normal map. Those maps are the targets of the
visibility loss.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch import Tensor

from core.config import AOConfig
from core.losses import depth_to_points
from core.model import GaussianModel
from core.render import RenderCamera, render
from native import gaussian_rays, gaussian_visibility, trace_visibility

__all__ = ["GaussianAOBaker", "init_visibility", "ao_map", "filter_torch", "map_scale",
           "scaled_camera"]


def scaled_camera(camera: RenderCamera, scale: float) -> RenderCamera:
    """The same camera at `scale` times the resolution (pixel centres stay consistent)."""
    w, h = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
    sx, sy = w / camera.width, h / camera.height
    K = camera.K.clone()
    K[0] *= sx  # rows, as core.data.Camera.scaled does
    K[1] *= sy
    return RenderCamera(camera.viewmat, K, w, h, camera.near)


def map_scale(camera: RenderCamera, config: AOConfig) -> float:
    """The traced map's scale for `camera`: `config.scale`, lowered so the map has at most
    `config.max_map_pixels` pixels."""
    cap = config.max_map_pixels
    if cap is None or camera.width * camera.height * config.scale ** 2 <= cap:
        return config.scale
    return math.sqrt(cap / (camera.width * camera.height))


@torch.no_grad()
def init_visibility(model: GaussianModel, optimizer=None, config: AOConfig = AOConfig()) -> Tensor:
    """Set the visibility attribute from ray tracing; returns the visibility (N,)."""
    vis = gaussian_visibility(model.means.detach(), model.quats.detach(),
                              model.scales.detach(), model.opacity_g.detach(),
                              model.normals.detach(), n_dirs=config.n_dirs)
    _assign(model, vis, optimizer)
    return vis


def _assign(model: GaussianModel, vis: Tensor, optimizer) -> None:
    p = vis.clamp(1e-4, 1 - 1e-4)
    model.assign("visibility", torch.log(p / (1 - p))[:, None], optimizer)


def _filter_size(config: AOConfig) -> int:
    return max(3, int(2 * math.ceil(2 * config.sigma_space) + 1))


def _filter(ao: np.ndarray, guide: np.ndarray, config: AOConfig) -> np.ndarray:
    """OpenCV's joint bilateral filter (contrib's ximgproc) of (H, W) `ao` by the (H, W, 3)
    normal `guide`."""
    return cv2.ximgproc.jointBilateralFilter(guide.astype(np.float32), ao.astype(np.float32),
                                             _filter_size(config), config.sigma_color,
                                             config.sigma_space)


def filter_torch(ao: Tensor, guide: Tensor, config: AOConfig) -> Tensor:
    """The same joint bilateral filter as OpenCV's ximgproc (a disc of radius d // 2, spatial
    weight exp(-r^2 / 2 sigma_space^2), range weight exp(-(L1 distance of the guides)^2 /
    2 sigma_color^2), borders reflected without repeating the edge) in torch, on the tensors'
    device: the bake stays on the GPU, and runs where OpenCV's contrib modules are missing.
    `ao` (H, W), `guide` (H, W, 3); returns (H, W)."""
    r = _filter_size(config) // 2
    h, w = ao.shape
    mode = "replicate" if min(h, w) <= r else "reflect"  # too small to reflect: repeat
    g = guide.permute(2, 0, 1).float()
    gp = torch.nn.functional.pad(g[None], (r, r, r, r), mode=mode)[0]
    ap = torch.nn.functional.pad(ao.float()[None, None], (r, r, r, r), mode=mode)[0, 0]
    acc, wsum = torch.zeros_like(ao, dtype=torch.float32), torch.zeros_like(ao, dtype=torch.float32)
    cs, ss = -0.5 / config.sigma_color ** 2, -0.5 / config.sigma_space ** 2
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dx * dx + dy * dy > r * r:
                continue
            dist = (gp[:, r + dy:r + dy + h, r + dx:r + dx + w] - g).abs().sum(0)
            weight = torch.exp(dist * dist * cs + (dx * dx + dy * dy) * ss)
            acc += weight * ap[r + dy:r + dy + h, r + dx:r + dx + w]
            wsum += weight
    return acc / wsum


@dataclass
class _Origins:
    """The rays one view's AO map traces: covered pixels of its 1/4-resolution render."""

    covered: Tensor
    """(h, w) pixels whose geometry coverage passes `min_alpha`."""
    normal: Tensor
    """(h, w, 3) unit rendered normals (the filter's guide)."""
    points: Tensor
    """(M, 3) surface points of the covered pixels with a usable normal."""
    normals: Tensor
    """(M, 3) their unit normals."""
    offset: Tensor
    """(M,) distance each ray starts above its surface (`AOConfig.offset_pixels`)."""
    ok: Tensor
    """(count of covered,) which covered pixels have a usable normal (the others stay 1)."""


def _origins(model: GaussianModel, camera: RenderCamera, beta: float,
             config: AOConfig) -> _Origins:
    small = scaled_camera(camera, map_scale(camera, config))
    r = render(model, small, sh_degree=0, beta=beta, geometry=True, tie_opacity=False)
    covered = r.alpha_g[..., 0] > config.min_alpha
    normal = torch.nn.functional.normalize(r.normal, dim=-1)
    points = depth_to_points(r.depth, small.K, small.viewmat)[covered]
    normals = normal[covered]
    ok = normals.norm(dim=-1) > 0.5
    footprint = r.depth[..., 0][covered] / camera.K[0, 0]
    return _Origins(covered, normal, points[ok].contiguous(), normals[ok].contiguous(),
                    config.offset_pixels * footprint[ok], ok)


def _map(o: _Origins, vis: Tensor, camera: RenderCamera, config: AOConfig) -> Tensor:
    """(H, W, 1) AO at the camera's full resolution from the traced visibility of `o`'s rays:
    upsampled, then joint-bilateral filtered by the normal map (OpenCV on the CPU, where its
    contrib modules are; else `filter_torch`, on the device)."""
    device = o.normal.device
    ao = torch.ones(o.covered.shape, device=device)
    inner = torch.ones(o.ok.shape[0], device=device)
    inner[o.ok] = vis.to(inner.dtype)
    ao[o.covered] = inner
    size = (camera.height, camera.width)
    up = torch.nn.functional.interpolate(ao[None, None], size=size, mode="bilinear",
                                         align_corners=False)[0, 0]
    guide = torch.nn.functional.interpolate(o.normal.permute(2, 0, 1)[None], size=size,
                                            mode="bilinear", align_corners=False)[0]
    if device.type == "cpu" and hasattr(cv2, "ximgproc"):
        filtered = torch.from_numpy(_filter(up.numpy(), guide.permute(1, 2, 0).numpy(), config))
    else:
        filtered = filter_torch(up, guide.permute(1, 2, 0), config)
    return filtered.clamp(0.0, 1.0).float()[..., None]


def _trace(model: GaussianModel, origins: Tensor, normals: Tensor, offset: Tensor,
           exclude: Tensor | None, config: AOConfig) -> Tensor:
    if not origins.shape[0]:
        return origins.new_ones(0)
    return trace_visibility(origins, normals, model.means.detach(), model.quats.detach(),
                            model.scales.detach(), model.opacity_g.detach(),
                            n_dirs=config.n_dirs, offset=offset, exclude=exclude)


@torch.no_grad()
def ao_map(model: GaussianModel, camera: RenderCamera, *, beta: float = 0.0,
           config: AOConfig = AOConfig()) -> Tensor:
    """(H, W, 1) ambient occlusion of one view at the camera's full resolution, on the model's
    device."""
    camera = camera.to(model.means.device)
    o = _origins(model, camera, beta, config)
    return _map(o, _trace(model, o.points, o.normals, o.offset, None, config), camera, config)


class GaussianAOBaker:
    """The trainer's AO hook: initialise per-Gaussian visibility, return per-view AO targets.

    Every ray of the bake, the Gaussians' own and every view's map, is traced in one call, so
    the tree over the Gaussians is built once rather than once per view."""

    def __init__(self, config: AOConfig = AOConfig()):
        self.config = config

    @torch.no_grad()
    def __call__(self, model: GaussianModel, cameras, optimizer=None, beta: float = 0.0):
        cfg, device = self.config, model.means.device
        cameras = [c.to(device) for c in cameras]
        views = [_origins(model, cam, beta, cfg) for cam in cameras]
        n = len(model)
        means = model.means.detach()
        own_offset, own_exclude = gaussian_rays(means, model.scales)  # gaussian_visibility's
        origins = torch.cat([means] + [o.points.to(means) for o in views])
        normals = torch.cat([model.normals.detach()] + [o.normals.to(means) for o in views])
        offset = torch.cat([own_offset] + [o.offset.to(means) for o in views])
        exclude = torch.cat([own_exclude,
                             torch.full((origins.shape[0] - n,), -1, device=device)])
        vis = _trace(model, origins, normals, offset, exclude, cfg)
        _assign(model, vis[:n], optimizer)
        parts = vis[n:].split([o.points.shape[0] for o in views])
        return [_map(o, v, cam, cfg) for o, v, cam in zip(views, parts, cameras)]
