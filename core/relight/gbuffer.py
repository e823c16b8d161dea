"""The G-buffer of a reconstructed frame seen from one camera (docs/design.md section 5, relighting):
base colour (SH degree 0), the view-dependent SH residual, normal, visibility, depth, coverage,
world positions; all linear light.

The model learnt colours as the capture stores them: sRGB-encoded for PNG/JPEG captures, linear
for EXR ones. Straight (unpremultiplied) colours are decoded to linear before any division; the
residual is the full-SH colour minus the degree-0 colour, both decoded, so base + residual gives
back the reconstruction's own colour under the capture light.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from core.color import srgb_to_linear
from core.config import Views, read_run
from core.data.layout import near_plane
from core.data.schema import load_capture
from core.render import RenderCamera, render, safe_divide
from core.stages import plan

__all__ = ["GBuffer", "RunRender", "gbuffer", "pixel_points", "run_render"]

# Coverage below which a pixel has no surface in the G-buffer (its normal and albedo are noise).
MIN_ALPHA = 1e-3


@dataclass(frozen=True)
class RunRender:
    """How a run's models are rendered at the end of training (from its `ResolvedRun`)."""

    sh_degree: int
    """SH degree of the last step."""
    beta: float
    """Opacity mixing of the last step."""
    eps2d: float
    """Mip-Splatting screen blur."""
    antialiased: bool
    """Mip-Splatting opacity compensation."""
    near: float
    """Near plane of the run's renders (`TrainConfig.near`)."""
    background: tuple[float, float, float]
    """Background colour as stored (sRGB for PNG captures)."""
    views: Views
    """The run's views: its cameras, held-out ones and resolution."""
    capture: Path
    """The capture the run was made from."""

    @property
    def downscale(self) -> float:
        """The run's image reduction (held-out renders are at this resolution)."""
        return self.views.downscale

    def camera(self, camera, device: torch.device | str = "cpu") -> RenderCamera:
        """`camera` (a `core.data.Camera`) as the run renders it: on `device`, with its near
        plane."""
        return RenderCamera.from_camera(camera, device=device, near=self.near)


def run_render(run_dir, capture_dir=None) -> RunRender:
    """How the run in `run_dir` renders (its RUN/config.json, `core.config.read_run`);
    ValueError when it is not a run directory or its capture is not there."""
    resolved = read_run(run_dir, capture_dir)
    train = resolved.config.train
    p = plan(train.schedule.iterations - 1, train.schedule, train.method)
    capture = Path(capture_dir if capture_dir is not None else resolved.capture)
    if not (capture / "capture.json").is_file():
        raise ValueError(f"capture_dir: {capture} has no capture.json (pass the capture folder)")
    near = train.near if train.near is not None else near_plane(load_capture(capture).cameras)
    return RunRender(p.sh_degree, p.beta, train.eps2d, train.antialiased, near,
                     tuple(train.background), resolved.views, capture)  # type: ignore[arg-type]


@dataclass
class GBuffer:
    """Per-pixel surface attributes of one view, (H, W, C) float32, linear light."""

    base: Tensor
    """(H, W, 3) straight base colour (SH degree 0), linear."""
    residual: Tensor
    """(H, W, 3) view-dependent part: full-SH colour minus base colour, linear."""
    normal: Tensor
    """(H, W, 3) unit world normal (0 where uncovered)."""
    visibility: Tensor
    """(H, W, 1) ambient visibility 0..1 (1 = unoccluded)."""
    depth: Tensor
    """(H, W, 1) expected camera depth of the geometry branch (0 where uncovered)."""
    alpha: Tensor
    """(H, W, 1) appearance coverage (what the colour is composited with)."""
    alpha_g: Tensor
    """(H, W, 1) geometry coverage."""
    points: Tensor
    """(H, W, 3) world positions from the depth (camera centre where depth is 0)."""


def pixel_points(camera: RenderCamera, depth: Tensor) -> Tensor:
    """World points (H, W, 3) at camera depth `depth` (H, W, 1) through each pixel centre."""
    h, w = camera.height, camera.width
    dev = depth.device
    v, u = torch.meshgrid(torch.arange(h, device=dev, dtype=torch.float32) + 0.5,
                          torch.arange(w, device=dev, dtype=torch.float32) + 0.5, indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1)
    rays = pix @ torch.linalg.inv(camera.K.to(dev)).T  # camera coordinates at z = 1
    cam = rays * depth
    R, t = camera.viewmat[:3, :3].to(dev), camera.viewmat[:3, 3].to(dev)
    return (cam - t) @ R  # R^T (p - t), row vectors


@torch.no_grad()
def gbuffer(model, camera: RenderCamera, settings: RunRender, *, linear_capture: bool) -> GBuffer:
    """Render the G-buffer of `model` from `camera` with the run's final settings; colours are
    decoded from sRGB unless `linear_capture` (an EXR capture)."""
    kw = dict(beta=settings.beta, geometry=True,
              background=torch.zeros(3, device=model.means.device),
              eps2d=settings.eps2d, antialiased=settings.antialiased)
    r0 = render(model, camera, sh_degree=0, **kw)
    rf = r0 if settings.sh_degree == 0 else render(model, camera, sh_degree=settings.sh_degree,
                                                   **kw)
    alpha = r0.alpha_c
    decode = (lambda x: x.clamp_min(0.0)) if linear_capture else srgb_to_linear
    base = decode(safe_divide(r0.rgb, alpha, MIN_ALPHA))
    full = decode(safe_divide(rf.rgb, alpha, MIN_ALPHA))
    covered = r0.alpha_g > MIN_ALPHA
    normal = torch.where(covered, torch.nn.functional.normalize(r0.normal, dim=-1),
                         torch.zeros_like(r0.normal))
    vis = safe_divide(r0.visibility, r0.alpha_g, MIN_ALPHA).clamp(0.0, 1.0)
    return GBuffer(base=base, residual=full - base, normal=normal, visibility=vis,
                   depth=r0.depth, alpha=alpha, alpha_g=r0.alpha_g,
                   points=pixel_points(camera, r0.depth))
