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

import cv2
import numpy as np
import torch
from torch import Tensor

from core.config import AOConfig
from core.losses import depth_to_points
from core.model import GaussianModel
from core.render import RenderCamera, render
from native import gaussian_visibility, trace_visibility

__all__ = ["GaussianAOBaker", "init_visibility", "ao_map", "scaled_camera"]


def scaled_camera(camera: RenderCamera, scale: float) -> RenderCamera:
    """The same camera at `scale` times the resolution (pixel centres stay consistent)."""
    w, h = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
    sx, sy = w / camera.width, h / camera.height
    K = camera.K.clone()
    K[0] *= sx  # rows, as core.data.Camera.scaled does
    K[1] *= sy
    return RenderCamera(camera.viewmat, K, w, h)


@torch.no_grad()
def init_visibility(model: GaussianModel, optimizer=None, config: AOConfig = AOConfig()) -> Tensor:
    """Set the visibility attribute from ray tracing; returns the visibility (N,)."""
    vis = gaussian_visibility(model.means.detach(), model.quats.detach(),
                              model.scales.detach(), model.opacity_g.detach(),
                              model.normals.detach(), n_dirs=config.n_dirs)
    p = vis.clamp(1e-4, 1 - 1e-4)
    model.assign("visibility", torch.log(p / (1 - p))[:, None], optimizer)
    return vis


def _filter(ao: np.ndarray, guide: np.ndarray, config: AOConfig) -> np.ndarray:
    if not hasattr(cv2, "ximgproc"):
        raise RuntimeError("AO baking needs OpenCV's contrib modules (ximgproc): install "
                           "opencv-contrib-python-headless instead of opencv-python-headless")
    d = max(3, int(2 * math.ceil(2 * config.sigma_space) + 1))
    return cv2.ximgproc.jointBilateralFilter(guide.astype(np.float32), ao.astype(np.float32),
                                             d, config.sigma_color, config.sigma_space)


@torch.no_grad()
def ao_map(model: GaussianModel, camera: RenderCamera, *, beta: float = 0.0,
           config: AOConfig = AOConfig()) -> Tensor:
    """(H, W, 1) ambient occlusion of one view at the camera's full resolution, on the model's
    device (the joint bilateral filter runs on the CPU, OpenCV)."""
    device = model.means.device
    camera = camera.to(device)
    small = scaled_camera(camera, config.scale)
    r = render(model, small, sh_degree=0, beta=beta, geometry=True, tie_opacity=False)
    covered = r.alpha_g[..., 0] > config.min_alpha
    normal = torch.nn.functional.normalize(r.normal, dim=-1)
    ao = torch.ones(small.height, small.width, device=device)
    if bool(covered.any()):
        points = depth_to_points(r.depth, small.K, small.viewmat)[covered]
        normals = normal[covered]
        ok = normals.norm(dim=-1) > 0.5
        depth = r.depth[..., 0][covered]
        footprint = depth / camera.K[0, 0]
        vis = torch.ones(points.shape[0], device=device)
        vis[ok] = trace_visibility(points[ok].contiguous(), normals[ok].contiguous(),
                                   model.means.detach(), model.quats.detach(),
                                   model.scales.detach(), model.opacity_g.detach(),
                                   n_dirs=config.n_dirs,
                                   offset=config.offset_pixels * footprint[ok])
        ao[covered] = vis
    size = (camera.height, camera.width)
    up = torch.nn.functional.interpolate(ao[None, None], size=size, mode="bilinear",
                                         align_corners=False)[0, 0]
    guide = torch.nn.functional.interpolate(normal.permute(2, 0, 1)[None], size=size,
                                            mode="bilinear", align_corners=False)[0]
    filtered = _filter(up.cpu().numpy(), guide.permute(1, 2, 0).cpu().numpy(), config)
    return torch.from_numpy(np.clip(filtered, 0.0, 1.0)).float()[..., None].to(device)


class GaussianAOBaker:
    """The trainer's AO hook: initialise per-Gaussian visibility, return per-view AO targets."""

    def __init__(self, config: AOConfig = AOConfig()):
        self.config = config

    def __call__(self, model: GaussianModel, cameras, optimizer=None, beta: float = 0.0):
        init_visibility(model, optimizer, self.config)
        return [ao_map(model, cam, beta=beta, config=self.config) for cam in cameras]
