"""Training losses of docs/design.md section 5, on (H, W, C) image tensors.

- photometric: (1 - 0.2) L1 + 0.2 D-SSIM, SSIM with an 11x11 Gaussian window, sigma 1.5
  (3DGS, Kerbl et al. 2023, lambda_dssim = 0.2; SSIM constants of Wang et al. 2004).
- normal prior: 0.2 L1 + 0.05 edge-aware smoothness |grad N| exp(-|grad N_prior|).
- depth-normal consistency: 0.01 mean(sg(O_g) - N . n(D)), n(D) the normal of the
  back-projected expected depth by central differences, in world space like N.
- sparsity (off by default): opacity_l1 mean(o) + scale_l1 mean(s) / extent, 3DGS-MCMC's
  regularizers (Kheradmand et al. 2024), the scale over the scene extent.
- visibility: 0.1 L1 + 0.01 smoothness |grad V| exp(-|grad N_prior|) (the paper's Eq. 10: AO
  may change across a crease of the prior normals; without a prior, unweighted).
The weights are the defaults of `LossWeights`; each function returns the weighted term.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor

from core.config import LossWeights

__all__ = [
    "blur",
    "depth_normal_consistency",
    "depth_to_normals",
    "depth_to_points",
    "coverage_l1",
    "geometry_mask_loss",
    "normal_prior_loss",
    "photometric_loss",
    "sparsity_loss",
    "ssim",
    "ssim_reference",
    "visibility_loss",
]


@functools.lru_cache(maxsize=8)
def _window_1d(size: int, sigma: float, device: torch.device = torch.device("cpu")) -> Tensor:
    # Computed on the CPU and cached per device: no host-to-device copy per call.
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return (g / g.sum()).float().to(device)


def _ssim_map(mu_x: Tensor, mu_y: Tensor, xx: Tensor, yy: Tensor, xy: Tensor) -> Tensor:
    sxx, syy, sxy = xx - mu_x * mu_x, yy - mu_y * mu_y, xy - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    return ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))


def _check_pair(a: Tensor, b: Tensor) -> None:
    if a.shape != b.shape or a.dim() != 3:
        raise ValueError(f"a, b: expected equal (H, W, C) shapes, got {tuple(a.shape)} and "
                         f"{tuple(b.shape)}")


def ssim(a: Tensor, b: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM of two (H, W, C) images in 0..1: Gaussian window, zero padding 'same' as in
    3DGS utils/loss_utils.py, C1 = 0.01^2, C2 = 0.03^2 (Wang et al. 2004).

    The window is the outer product of a 1D Gaussian, so the five local means (x, y, x^2, y^2,
    xy) are one pass of 1D convolutions along rows and one along columns over the five stacked
    (a zero-padded separable filter equals the 2D one exactly); `ssim_reference` is the 2D
    form."""
    _check_pair(a, b)
    c = a.shape[2]
    g = _window_1d(window, sigma, a.device).to(a)
    x, y = a.permute(2, 0, 1), b.permute(2, 0, 1)
    stack = torch.cat([x, y, x * x, y * y, x * y])[None]  # (1, 5C, H, W)
    k = 5 * c
    pad = window // 2
    rows = F.conv2d(stack, g.view(1, 1, 1, window).expand(k, 1, 1, window), padding=(0, pad),
                    groups=k)
    mean = F.conv2d(rows, g.view(1, 1, window, 1).expand(k, 1, window, 1), padding=(pad, 0),
                    groups=k)[0]
    return _ssim_map(*mean.split(c)).mean()


def ssim_reference(a: Tensor, b: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """`ssim` with the 2D window: five 11x11 convolutions (the definition, for tests)."""
    _check_pair(a, b)
    c = a.shape[2]
    g = _window_1d(window, sigma, a.device).to(a)
    w = (g[:, None] * g[None, :]).expand(c, 1, window, window)
    x, y = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]

    def blur(t: Tensor) -> Tensor:
        return F.conv2d(t, w, padding=window // 2, groups=c)

    return _ssim_map(blur(x), blur(y), blur(x * x), blur(y * y), blur(x * y)).mean()


@functools.lru_cache(maxsize=16)
def _blur_kernel(sigma: float, device: torch.device = torch.device("cpu")) -> Tensor:
    # Computed on the CPU and cached per device: no host-to-device copy per call.
    radius = max(1, int(3 * sigma + 0.5))
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return (g / g.sum()).float().to(device)


def blur(image: Tensor, sigma: float) -> Tensor:
    """(H, W, C) image blurred by a separable Gaussian of `sigma` pixels (replicated edges);
    returned unchanged for sigma < 0.3."""
    if sigma < 0.3:
        return image
    k = _blur_kernel(float(sigma), image.device).to(image)
    c, r = image.shape[2], k.shape[0] // 2
    x = image.permute(2, 0, 1)[None]
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).expand(c, 1, 1, -1),
                 groups=c)
    x = F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1).expand(c, 1, -1, 1),
                 groups=c)
    return x[0].permute(1, 2, 0)


def photometric_loss(pred: Tensor, target: Tensor, weights: LossWeights = LossWeights()) -> Tensor:
    """(1 - dssim) L1 + dssim (1 - SSIM) over (H, W, 3) images."""
    l1 = (pred - target).abs().mean()
    return (1 - weights.dssim) * l1 + weights.dssim * (1 - ssim(pred, target))


def _dx(t: Tensor) -> Tensor:
    return t[:, 1:] - t[:, :-1]


def _dy(t: Tensor) -> Tensor:
    return t[1:] - t[:-1]


def normal_prior_loss(normal: Tensor, prior: Tensor, mask: Tensor | None = None,
                      weights: LossWeights = LossWeights(),
                      confidence: Tensor | None = None,
                      measured: Tensor | None = None) -> Tensor:
    """0.2 L1(N, N_prior) + 0.05 mean(|grad N| exp(-|grad N_prior|)) on (H, W, 3) maps.

    Only pixels with a prior (non-zero vector) and inside `mask` (H, W, 1) count for the L1; the
    smoothness uses forward differences with both pixels valid, |.| the channel mean of |diff|.
    `confidence` (H, W, 1) in 0..1 weighs each pixel as `weights.normal_confidence` says:
    `per_view`, the means are over the confidences (a pair: weighed and counted by the product
    of its two), so a confidence ranks a view's pixels against each other; `absolute`, the means
    stay over the pixels (pairs) with a prior (a pair as sure as the less sure of its two), so a
    view whose priors all have confidence 0.5 pulls half as hard as one whose priors are sure;
    `by_source`, `per_view` where `measured` (H, W, 1) is 1 (stereo's plane fits: a ramp on the
    fit's residual) and `absolute` where it is 0 (the visual hull's guess; a pair with one such
    pixel too). None `measured`: every confidence is a measurement's.
    """
    if normal.shape != prior.shape or normal.shape[-1] != 3:
        raise ValueError(f"normal, prior: expected equal (H, W, 3) shapes, got "
                         f"{tuple(normal.shape)} and {tuple(prior.shape)}")
    valid = (prior.abs().sum(dim=-1, keepdim=True) > 0).float()
    if mask is not None:
        valid = valid * (mask > 0.5).float()
    # Per pixel: `weight` pulls it, `count` is what it adds to the mean's denominator;
    # `absolute` 1 where its confidence is counted as a pixel, 0 where as its value.
    weight = count = valid
    absolute = None
    if confidence is not None:
        weight = valid * confidence
        mode = weights.normal_confidence
        if mode == "absolute":
            absolute = torch.ones_like(weight)
        elif mode == "by_source" and measured is not None:
            absolute = 1.0 - (measured > 0.5).float()
        count = weight if absolute is None else \
            absolute * (weight > 0).float() + (1.0 - absolute) * weight
    l1 = ((normal - prior).abs().mean(dim=-1, keepdim=True) * weight).sum() \
        / count.sum().clamp_min(1.0)
    smooth = normal.new_zeros(())
    for d, a, b in ((_dx, (slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                    (_dy, (slice(1, None),), (slice(None, -1),))):
        g = d(normal).abs().mean(dim=-1, keepdim=True)
        edge = torch.exp(-d(prior).abs().mean(dim=-1, keepdim=True))
        pull = part = weight[a] * weight[b]  # per view: the product, weighed and counted
        if absolute is not None:
            # a pair with an absolute pixel: as sure as its less sure pixel, counted as one
            either = torch.maximum(absolute[a], absolute[b])
            pull = either * torch.minimum(weight[a], weight[b]) + (1.0 - either) * pull
            part = either * (part > 0).float() + (1.0 - either) * part
        smooth = smooth + ((g * edge) * pull).sum() / part.sum().clamp_min(1)
    return weights.normal_l1 * l1 + weights.normal_smooth * smooth


def depth_to_points(depth: Tensor, K: Tensor, viewmat: Tensor) -> Tensor:
    """Back-project an (H, W, 1) camera-z depth map to world points (H, W, 3).

    Pixel (u, v) has its centre at (u + 0.5, v + 0.5); X_cam = z K^-1 (u+0.5, v+0.5, 1);
    X_world = R^T (X_cam - t) with viewmat = [R t] world-to-camera.
    """
    h, w = depth.shape[:2]
    v, u = torch.meshgrid(torch.arange(h, dtype=depth.dtype, device=depth.device) + 0.5,
                          torch.arange(w, dtype=depth.dtype, device=depth.device) + 0.5,
                          indexing="ij")
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    rays = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], dim=-1)
    cam = rays * depth
    R, t = viewmat[:3, :3].to(depth), viewmat[:3, 3].to(depth)
    return (cam - t) @ R  # row-vector form of R^T (x - t)


def depth_to_normals(depth: Tensor, K: Tensor, viewmat: Tensor) -> Tensor:
    """World normals (H-2, W-2, 3) of the interior pixels from central differences of the
    back-projected depth, oriented towards the camera.

    With OpenCV axes (x right, y down, z forward), dX/du x dX/dv points away from the camera, so
    the camera-facing normal is dX/dv x dX/du (a rotation keeps cross products).
    """
    p = depth_to_points(depth, K, viewmat)
    du = p[1:-1, 2:] - p[1:-1, :-2]
    dv = p[2:, 1:-1] - p[:-2, 1:-1]
    return F.normalize(torch.cross(dv, du, dim=-1), dim=-1)


def depth_normal_consistency(normal: Tensor, depth: Tensor, alpha_g: Tensor, K: Tensor,
                             viewmat: Tensor, weights: LossWeights = LossWeights(),
                             min_alpha: float = 0.5) -> Tensor:
    """0.01 mean(sg(O_g) - N . n(D)) over interior pixels whose 3x3 neighbourhood is covered
    (alpha_g > min_alpha; elsewhere the expected depth is meaningless).

    `normal` is the rendered, unnormalized (H, W, 3) normal (about O_g n), so the term is 0 when
    the rendered normal agrees with the depth's; `depth` is the expected depth (H, W, 1).
    """
    if depth.shape[:2] != normal.shape[:2] or alpha_g.shape != depth.shape:
        raise ValueError(f"normal, depth, alpha_g: expected (H, W, 3), (H, W, 1), (H, W, 1), got "
                         f"{tuple(normal.shape)}, {tuple(depth.shape)}, {tuple(alpha_g.shape)}")
    if depth.shape[0] < 3 or depth.shape[1] < 3:
        return normal.sum() * 0.0
    n_d = depth_to_normals(depth, K, viewmat)
    a = alpha_g.detach()
    covered = (a > min_alpha).float()
    # min-pool: a pixel counts when its whole 3x3 neighbourhood is covered
    valid = -F.max_pool2d(-covered.permute(2, 0, 1)[None], 3, stride=1)[0].permute(1, 2, 0)
    term = a[1:-1, 1:-1] - (normal[1:-1, 1:-1] * n_d).sum(dim=-1, keepdim=True)
    return weights.consistency * (term * valid).sum() / valid.sum().clamp_min(1.0)


def visibility_loss(visibility: Tensor, target: Tensor, mask: Tensor | None = None,
                    weights: LossWeights = LossWeights(), prior: Tensor | None = None) -> Tensor:
    """0.1 L1(V, V_target) + 0.01 mean(|grad V| exp(-|grad N_prior|)) on (H, W, 1) maps (mask:
    pixels that count; `prior` (H, W, 3) normals, None: the smoothness unweighted), |grad N|
    the channel mean of |diff| as in `normal_prior_loss`."""
    if visibility.shape != target.shape:
        raise ValueError(f"visibility, target: expected equal shapes, got "
                         f"{tuple(visibility.shape)} and {tuple(target.shape)}")
    if prior is not None and prior.shape[:2] != visibility.shape[:2]:
        raise ValueError(f"prior: expected ({visibility.shape[0]}, {visibility.shape[1]}, 3) "
                         f"normals, got {tuple(prior.shape)}")
    m = torch.ones_like(target) if mask is None else (mask > 0.5).to(target)
    l1 = ((visibility - target).abs() * m).sum() / m.sum().clamp_min(1.0)
    smooth = visibility.new_zeros(())
    for d in (_dx, _dy):
        g = d(visibility).abs()
        if prior is not None:
            g = g * torch.exp(-d(prior).abs().mean(dim=-1, keepdim=True))
        smooth = smooth + g.mean()
    return weights.visibility_l1 * l1 + weights.visibility_smooth * smooth


def coverage_l1(alpha: Tensor, mask: Tensor) -> Tensor:
    """mean |alpha - mask| over an (H, W, 1) image: how far a rendered coverage is from the
    capture's coverage mask."""
    if alpha.shape != mask.shape:
        raise ValueError(f"alpha, mask: expected equal shapes, got {tuple(alpha.shape)} "
                         f"and {tuple(mask.shape)}")
    return (alpha - mask).abs().mean()


def geometry_mask_loss(alpha_g: Tensor, mask: Tensor,
                       weights: LossWeights = LossWeights()) -> Tensor:
    """w * mean |alpha_g - mask| over the (H, W, 1) image: the geometry branch covers what the
    capture's coverage mask covers, and nothing else."""
    return weights.geometry_mask * coverage_l1(alpha_g, mask)


def sparsity_loss(opacities: list[Tensor], scales: Tensor, extent: float,
                  weights: LossWeights = LossWeights()) -> Tensor:
    """w_o * mean opacity (over each of `opacities`, (N,) in 0..1, summed) + w_s * mean of the
    (N, 3) `scales` / `extent`: 3DGS-MCMC's opacity and scale regularizers (module docstring).
    Zero weights give an exact 0 with no graph."""
    if extent <= 0:
        raise ValueError(f"extent: expected > 0, got {extent}")
    loss = scales.new_zeros(())
    if weights.opacity_l1 > 0:
        loss = loss + weights.opacity_l1 * sum(o.mean() for o in opacities)
    if weights.scale_l1 > 0:
        loss = loss + weights.scale_l1 * scales.mean() / extent
    return loss
