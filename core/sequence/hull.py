"""Which Gaussians belong to the subject: those inside the hull of the views' subject masks.

A point is inside a view's silhouette when it projects in front of the camera, into the picture,
onto a mask pixel (the mask dilated by `dilate` pixels, so Gaussians on the subject's rim, and a
subject that moved a little since, stay in). A visual hull keeps the points inside every view
that sees them; one wrong mask would then cut a limb off, so a point here is the subject's when
it is inside at least `share` of the masked views that see it. A static background point behind
the subject from a few views is inside only those few; one seen by no masked view is not the
subject's.

Tracked frames of a scene move only these (`core.sequence.tracker`), and a subject export keeps
only these (`core.export`).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["dilate", "inside_hull"]


def dilate(mask: Tensor, pixels: int) -> Tensor:
    """(H, W, 1) coverage mask grown by `pixels` (a square max filter); as is for 0."""
    if pixels <= 0:
        return mask
    m = mask.permute(2, 0, 1)[None]
    return F.max_pool2d(m, 2 * pixels + 1, stride=1, padding=pixels)[0].permute(1, 2, 0)


@torch.no_grad()
def inside_hull(means: Tensor, cameras: Sequence, masks: Sequence[Tensor | None], *,
                dilate_pixels: int = 4, share: float = 0.8, near: float = 0.01) -> Tensor:
    """(N,) bool: `means` (N, 3) inside at least `share` of the masked views that see them
    (module docstring). `cameras` are `core.render.RenderCamera`s (viewmat, K, width, height),
    `masks` their (H, W, 1) coverage in 0..1 (None: the view has none and does not vote)."""
    if len(cameras) != len(masks):
        raise ValueError(f"masks: expected one per camera ({len(cameras)}), got {len(masks)}")
    if not 0 < share <= 1:
        raise ValueError(f"share: expected a fraction in (0, 1], got {share}")
    pts = means.detach().float()
    seen = torch.zeros(pts.shape[0], device=pts.device)
    inside = torch.zeros_like(seen)
    for cam, mask in zip(cameras, masks):
        if mask is None:
            continue
        if tuple(mask.shape) != (cam.height, cam.width, 1):
            raise ValueError(f"masks: expected ({cam.height}, {cam.width}, 1) for its camera, "
                             f"got {tuple(mask.shape)}")
        grown = dilate(mask.to(pts.device).float(), dilate_pixels)[..., 0] > 0.5
        local = pts @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
        z = local[:, 2]
        uv = (local[:, :2] / z.clamp_min(near)[:, None]) @ cam.K[:2, :2].T + cam.K[:2, 2]
        u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        visible = (z > near) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
        hit = torch.zeros_like(visible)
        hit[visible] = grown[v[visible], u[visible]]
        seen += visible.float()
        inside += hit.float()
    return (seen > 0) & (inside >= share * seen - 1e-6)
