"""Rendering a GaussianModel from one camera: SH colour, geometry features, a typed result.

Colour is evaluated from SH along the view direction (camera centre to each mean) and offset by
0.5 then clamped at 0, as in 3DGS (Kerbl et al. 2023, gaussian_renderer/__init__.py). The
geometry features are [normal (3), visibility (1)] blended with the geometry alpha; beta mixing
of the two opacities happens inside the rasterizer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

import native
from core.model import GaussianModel
from native.types import RasterOutput

__all__ = ["NEAR", "Render", "RenderCamera", "eval_sh", "render", "safe_divide", "seen_directions"]

NEAR = 0.01
"""The rasterizer's near plane, what a camera clips at unless a run gives its own."""

# Real SH constants of the 3DGS implementation (utils/sh_utils.py, after the PlenOctree code).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """Real SH basis (..., (degree+1)^2) at unit directions (..., 3), in the 3DGS order/signs."""
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"degree: expected 0, 1, 2 or 3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree > 0:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz,
                SH_C2[4] * (xx - yy)]
    if degree > 2:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def eval_sh(sh: Tensor, dirs: Tensor, degree: int) -> Tensor:
    """Evaluate SH coefficients (N, K>=(degree+1)^2, C) at unit directions (N, 3) -> (N, C)."""
    k = (degree + 1) ** 2
    if sh.dim() != 3 or sh.shape[1] < k:
        raise ValueError(f"sh: expected shape (N, >={k}, C) for degree {degree}, "
                         f"got {tuple(sh.shape)}")
    basis = sh_basis(dirs, degree)
    return (basis[:, :, None] * sh[:, :k]).sum(dim=1)


@dataclass(frozen=True)
class RenderCamera:
    """A pinhole camera as the rasterizer wants it (float32 tensors, OpenCV axes)."""

    viewmat: Tensor
    """(4, 4) world-to-camera."""
    K: Tensor
    """(3, 3) intrinsics."""
    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    near: float = NEAR
    """Near plane (camera depth): nothing closer is drawn. A run's cameras take its
    `TrainConfig.near`, the rig's, resolved with the run."""

    @classmethod
    def from_camera(cls, camera, device: torch.device | str = "cpu",
                    near: float = NEAR) -> RenderCamera:
        """From a `core.data.Camera` (numpy float64), with its tensors on `device`."""
        if not near > 0:
            raise ValueError(f"near: expected a positive camera depth, got {near}")
        return cls(torch.from_numpy(np.asarray(camera.world_to_camera, np.float32)).contiguous()
                   .to(device),
                   torch.from_numpy(np.asarray(camera.K, np.float32)).contiguous().to(device),
                   int(camera.width), int(camera.height), float(near))

    def to(self, device: torch.device | str) -> RenderCamera:
        """This camera with its tensors on `device` (itself when they are there already)."""
        viewmat, K = self.viewmat.to(device), self.K.to(device)
        if viewmat is self.viewmat and K is self.K:
            return self
        return RenderCamera(viewmat, K, self.width, self.height, self.near)

    @property
    def center(self) -> Tensor:
        """(3,) camera centre in world coordinates, -R^T t."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t


@dataclass
class Render:
    """One rendered view. Image fields are (H, W, channels)."""

    rgb: Tensor
    """(H, W, 3) colour including the background."""
    normal: Tensor
    """(H, W, 3) alpha_g-weighted world normals, not normalized (zero without the branch)."""
    depth: Tensor
    """(H, W, 1) expected camera depth, raw depth / alpha_g (0 where alpha_g is ~0)."""
    visibility: Tensor
    """(H, W, 1) alpha_g-weighted visibility."""
    alpha_c: Tensor
    """(H, W, 1) appearance coverage."""
    alpha_g: Tensor
    """(H, W, 1) geometry coverage."""
    raster: RasterOutput
    """The rasterizer's output (means2d, radii, AbsGS statistics, contribution)."""


def safe_divide(num: Tensor, den: Tensor, eps: float = 1e-6) -> Tensor:
    """num / den where den > eps, else 0, with finite gradients everywhere."""
    ok = den > eps
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def render(
    model: GaussianModel,
    camera: RenderCamera,
    *,
    sh_degree: int = 3,
    beta: float = 0.0,
    geometry: bool = True,
    tie_opacity: bool = False,
    background: Tensor | None = None,
    eps2d: float = 0.1,
    antialiased: bool = True,
    backend: native.Backend = "native",
    validate: bool = True,
) -> Render:
    """Render `model` from `camera`.

    `geometry=False` runs the appearance branch only (stage 1); `tie_opacity=True` passes the
    appearance opacity for the geometry one too (opacity_g tied to opacity_c, so that beta mixing
    leaves the appearance opacity unchanged). The defaults eps2d 0.1, antialiased follow the
    Mip-Splatting 2D filter of docs/design.md section 5; nothing nearer than the camera's
    `near` is drawn. Renders on the model's device; a camera or background elsewhere is copied
    there (give a trainer's cameras that device once, so no step pays for the copy). `validate=False` skips the rasterizer's per-element checks of the
    values (a training loop's later steps: the model's activations keep them valid).
    """
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"sh_degree: expected 0..3, got {sh_degree}")
    means = model.means
    if background is None:
        background = torch.zeros(3, device=means.device)
    camera = camera.to(means.device)
    dirs = torch.nn.functional.normalize(means - camera.center[None], dim=-1)
    # At degree 0 only sh0 enters the graph: the higher coefficients get no gradient (None,
    # not zeros), so the optimizer skips them instead of updating 45 numbers per Gaussian.
    sh = model.params["sh0"] if sh_degree == 0 else model.sh
    colors = torch.clamp_min(eval_sh(sh, dirs, sh_degree) + 0.5, 0.0)
    opacity_c = model.opacity_c
    opacity_g = opacity_c if tie_opacity else model.opacity_g
    features = torch.cat([model.normals, model.visibility], dim=1) if geometry else None
    out = native.rasterize(
        means, model.quats.contiguous(), model.scales.contiguous(), opacity_c.contiguous(),
        opacity_g.contiguous(), colors.contiguous(), features, camera.viewmat, camera.K,
        camera.width, camera.height, beta=float(beta), eps2d=eps2d, antialiased=antialiased,
        near=camera.near, background=background.to(means.device, means.dtype), backend=backend,
        validate=validate)
    if geometry:
        normal, visibility = out.geometry[..., :3], out.geometry[..., 3:4]
    else:
        normal = out.color.new_zeros(camera.height, camera.width, 3)
        visibility = out.color.new_zeros(camera.height, camera.width, 1)
    return Render(rgb=out.color, normal=normal, depth=safe_divide(out.depth, out.alpha_g),
                  visibility=visibility, alpha_c=out.alpha_c, alpha_g=out.alpha_g, raster=out)


@torch.no_grad()
def seen_directions(model: GaussianModel, cameras: list[RenderCamera], *, eps2d: float = 0.1,
                    antialiased: bool = True) -> Tensor:
    """(N, 3): per Gaussian, the sum of unit directions towards the cameras that see its centre,
    zero for a Gaussian no camera sees. A camera sees it when the centre projects into the
    image and its depth is at most the rendered expected depth there (appearance opacity) plus
    twice its largest scale: the surface in front of a Gaussian on the far side of a body hides
    it, while a Gaussian inside the surface's own blended shell still counts."""
    out = torch.zeros_like(model.means)
    slack = 2.0 * model.scales.max(dim=1).values
    for camera in cameras:
        camera = camera.to(model.means.device)
        # Tied opacities: the geometry alpha that weights the depth is the appearance one.
        r = render(model, camera, sh_degree=0, geometry=True, tie_opacity=True, eps2d=eps2d,
                   antialiased=antialiased)
        depth = r.depth[..., 0]
        uv = r.raster.means2d.floor().long()
        z = model.means @ camera.viewmat[:3, :3].T + camera.viewmat[:3, 3]
        inside = ((uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0)
                  & (uv[:, 1] < camera.height) & (z[:, 2] > 0))
        u = uv[:, 0].clamp(0, camera.width - 1)
        v = uv[:, 1].clamp(0, camera.height - 1)
        d = depth[v, u]
        seen = inside & (d > 0) & (z[:, 2] <= d + slack)
        to_cam = torch.nn.functional.normalize(camera.center[None] - model.means, dim=-1)
        out += seen[:, None] * to_cam
    return out
