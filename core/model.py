"""The disentangled Gaussian model: raw parameters, their activations, optimizer groups and PLY.

Every Gaussian carries an appearance opacity and a geometry opacity (mixed by beta in the
rasterizer), view-dependent colour as SH coefficients of degree 0..3, and a geometry branch:
a normal and a visibility (ambient occlusion) value. Parameters are stored raw, as in 3DGS:
log-scales, opacity logits, unnormalized quaternions and normals, a visibility logit.

Adding or removing Gaussians goes through :meth:`GaussianModel.extend` and
:meth:`GaussianModel.keep`, which edit the Adam moments along with the tensors so the optimizer
never sees a parameter whose state has another length.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from core.config import LearningRates
from core.plyio import read_gaussian_ply, write_gaussian_ply
from native.reference import quat_to_rotmat

__all__ = [
    "PARAM_NAMES",
    "SH_C0",
    "GaussianModel",
    "means_lr",
]

# 3DGS (Kerbl et al. 2023, utils/sh_utils.py RGB2SH): the degree-0 real SH constant 1/(2 sqrt(pi)).
SH_C0 = 0.28209479177387814

PARAM_NAMES: tuple[str, ...] = (
    "means", "scales", "quats", "sh0", "shN", "opacity_c", "opacity_g", "normals", "visibility",
)


def means_lr(rates: LearningRates, extent: float, step: int) -> float:
    """Exponentially decayed position rate at `step` (3DGS get_expon_lr_func without delay)."""
    t = min(max(step / max(rates.means_decay_steps, 1), 0.0), 1.0)
    lr0, lr1 = rates.means * extent, rates.means_final * extent
    return math.exp((1 - t) * math.log(lr0) + t * math.log(lr1))


def _nn_sq_dist(points: Tensor, k: int = 3) -> Tensor:
    """Mean squared distance to the k nearest other points (N,), by a k-d tree (float64)."""
    n = points.shape[0]
    k = min(k, n - 1)
    if k <= 0:
        return torch.full((n,), 1e-4, dtype=points.dtype, device=points.device)
    pts = points.detach().cpu().double().numpy()
    # Each point is its own nearest (at 0); where points coincide, a twin may come first
    # instead, which leaves the same distances.
    dist, _ = cKDTree(pts).query(pts, k=k + 1)
    return torch.from_numpy(np.square(dist[:, 1:]).mean(axis=1)).to(points)


class GaussianModel:
    """N disentangled Gaussians as raw parameters (`params`), with activated views as properties.

    Shapes: means (N,3), scales (N,3) log, quats (N,4) w,x,y,z, sh0 (N,1,3), shN (N,15,3),
    opacity_c (N,) logit, opacity_g (N,) logit, normals (N,3) unnormalized, visibility (N,1) logit.
    Every parameter lives on one device, the means' (`device`; `to` moves them all).
    """

    def __init__(self, params: dict[str, Tensor]):
        missing = [name for name in PARAM_NAMES if name not in params]
        if missing:
            raise ValueError(f"params: missing {missing}; expected every name in {PARAM_NAMES}")
        n = params["means"].shape[0]
        shapes = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "sh0": (n, 1, 3),
                  "shN": (n, 15, 3), "opacity_c": (n,), "opacity_g": (n,), "normals": (n, 3),
                  "visibility": (n, 1)}
        for name, shape in shapes.items():
            if tuple(params[name].shape) != shape:
                raise ValueError(f"params[{name!r}]: expected shape {shape}, "
                                 f"got {tuple(params[name].shape)}")
        device = params["means"].device
        elsewhere = [name for name in PARAM_NAMES if params[name].device != device]
        if elsewhere:
            raise ValueError(f"params: {elsewhere} are not on {device} like means; move every "
                             "parameter to one device")
        self.params: dict[str, torch.nn.Parameter] = {
            name: torch.nn.Parameter(params[name].detach().clone().float().contiguous())
            for name in PARAM_NAMES}

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def from_points(cls, points: Tensor, colors: Tensor | None = None, *,
                    opacity: float = 0.1, visibility: float = 0.9) -> GaussianModel:
        """Isotropic Gaussians at `points` (N,3), scale = sqrt of the mean squared distance to the
        3 nearest neighbours (3DGS create_from_pcd), opacity 0.1, colours (N,3) in 0..1 as SH
        degree 0 (grey when None), normals +z until the geometry branch starts."""
        if points.dim() != 2 or points.shape[1] != 3 or points.shape[0] == 0:
            raise ValueError(f"points: expected shape (N, 3) with N > 0, got {tuple(points.shape)}")
        pts = points.detach().float()
        n, dev = pts.shape[0], pts.device
        if colors is None:
            colors = torch.full((n, 3), 0.5, device=dev)
        if tuple(colors.shape) != (n, 3):
            raise ValueError(f"colors: expected shape ({n}, 3), got {tuple(colors.shape)}")
        dist = torch.sqrt(_nn_sq_dist(pts).clamp_min(1e-7))
        # The initial logits in float64, rounded once to the parameters' float32.
        opacity_logit, visibility_logit = torch.logit(
            torch.tensor([opacity, visibility], dtype=torch.float64)).tolist()
        quats = torch.zeros(n, 4, device=dev)
        quats[:, 0] = 1.0
        return cls({
            "means": pts,
            "scales": torch.log(dist)[:, None].repeat(1, 3),
            "quats": quats,
            "sh0": ((colors.to(dev).float() - 0.5) / SH_C0)[:, None, :],
            "shN": torch.zeros(n, 15, 3, device=dev),
            "opacity_c": torch.full((n,), opacity_logit, device=dev),
            "opacity_g": torch.full((n,), opacity_logit, device=dev),
            "normals": torch.tensor([[0.0, 0.0, 1.0]], device=dev).repeat(n, 1),
            "visibility": torch.full((n, 1), visibility_logit, device=dev),
        })

    @property
    def device(self) -> torch.device:
        """The device every parameter lives on."""
        return self.params["means"].device

    def to(self, device: torch.device | str) -> GaussianModel:
        """This model on `device`: itself when it is there already, else a copy (an optimizer
        made for this one does not follow; make another)."""
        target = torch.device(device)
        if target.type == "cuda" and target.index is None:
            target = torch.device("cuda", torch.cuda.current_device())
        if self.device == target:
            return self
        return GaussianModel({k: v.detach().to(device) for k, v in self.params.items()})

    # -- activations -----------------------------------------------------------------------
    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @property
    def means(self) -> Tensor:
        return self.params["means"]

    @property
    def scales(self) -> Tensor:
        return torch.exp(self.params["scales"])

    @property
    def quats(self) -> Tensor:
        return torch.nn.functional.normalize(self.params["quats"], dim=-1)

    @property
    def opacity_c(self) -> Tensor:
        return torch.sigmoid(self.params["opacity_c"])

    @property
    def opacity_g(self) -> Tensor:
        return torch.sigmoid(self.params["opacity_g"])

    @property
    def normals(self) -> Tensor:
        return torch.nn.functional.normalize(self.params["normals"], dim=-1)

    @property
    def visibility(self) -> Tensor:
        return torch.sigmoid(self.params["visibility"])

    @property
    def sh(self) -> Tensor:
        """(N, 16, 3) all SH coefficients."""
        return torch.cat([self.params["sh0"], self.params["shN"]], dim=1)

    # -- optimizer -------------------------------------------------------------------------
    def make_optimizer(self, rates: LearningRates = LearningRates(),
                       extent: float = 1.0) -> torch.optim.Adam:
        """One Adam with one named group per parameter (eps 1e-15 as in 3DGS), fused: one
        kernel a group where torch's default runs about ten a group (docs/benchmarks.md, "A
        step's host syncs"; the same updates to float rounding)."""
        if not extent > 0:
            raise ValueError(f"extent: expected a positive scene extent, got {extent}")
        groups = [{"params": [p], "lr": rates.for_param(name, extent), "name": name}
                  for name, p in self.params.items()]
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)

    def _edit(self, optimizer: torch.optim.Optimizer | None,
              edit: Callable[[str, Tensor, bool], Tensor]) -> None:
        """Replace every parameter by edit(name, tensor, is_state=False) and every per-Gaussian
        Adam moment by edit(name, moment, is_state=True), keeping the groups pointing at them."""
        new = {name: torch.nn.Parameter(edit(name, p.detach(), False).contiguous())
               for name, p in self.params.items()}
        if optimizer is not None:
            for group in optimizer.param_groups:
                name = group["name"]
                old = group["params"][0]
                state = optimizer.state.pop(old, None)
                group["params"][0] = new[name]
                if state is not None:
                    for key, value in state.items():
                        if isinstance(value, Tensor) and value.shape == old.shape:
                            state[key] = edit(name, value, True).contiguous()
                    optimizer.state[new[name]] = state
        self.params = new

    def extend(self, values: dict[str, Tensor],
               optimizer: torch.optim.Optimizer | None = None) -> None:
        """Append Gaussians given as raw values per parameter; their Adam moments start at 0."""
        m = values["means"].shape[0]
        for name in PARAM_NAMES:
            v = values.get(name)
            if v is None or v.shape[0] != m:
                raise ValueError(f"values[{name!r}]: expected {m} rows like means")

        def edit(name: str, t: Tensor, is_state: bool) -> Tensor:
            extra = torch.zeros_like(values[name]) if is_state else values[name].detach()
            return torch.cat([t, extra.to(t.dtype)], dim=0)

        self._edit(optimizer, edit)

    def keep(self, mask: Tensor, optimizer: torch.optim.Optimizer | None = None) -> None:
        """Keep the Gaussians where the boolean `mask` (N,) is True (moments indexed alike)."""
        if mask.dtype != torch.bool or tuple(mask.shape) != (len(self),):
            raise ValueError(f"mask: expected a bool tensor of shape ({len(self)},), "
                             f"got {mask.dtype} {tuple(mask.shape)}")
        self._edit(optimizer, lambda name, t, is_state: t[mask])

    def replace_rows(self, rows: Tensor, values: dict[str, Tensor],
                     optimizer: torch.optim.Optimizer | None = None) -> None:
        """Overwrite the Gaussians at `rows` (distinct indices) with raw `values` per
        parameter, their Adam moments zeroed (a relocation: the rows are new Gaussians)."""
        if rows.dim() != 1 or rows.numel() != rows.unique().numel():
            raise ValueError("rows: expected distinct indices in one dimension")
        for name in PARAM_NAMES:
            v = values.get(name)
            if v is None or v.shape != (rows.numel(), *self.params[name].shape[1:]):
                raise ValueError(f"values[{name!r}]: expected {rows.numel()} rows of "
                                 f"{tuple(self.params[name].shape[1:])}")

        def edit(name: str, t: Tensor, is_state: bool) -> Tensor:
            t = t.clone()
            t[rows] = 0 if is_state else values[name].detach().to(t.dtype)
            return t

        self._edit(optimizer, edit)

    def assign(self, name: str, values: Tensor,
               optimizer: torch.optim.Optimizer | None = None) -> None:
        """Overwrite one parameter in place of its values and zero its Adam moments (used by the
        opacity reset and by the start of the geometry branch)."""
        if name not in self.params:
            raise ValueError(f"name: expected one of {PARAM_NAMES}, got {name!r}")
        if values.shape != self.params[name].shape:
            raise ValueError(f"values: expected shape {tuple(self.params[name].shape)}, "
                             f"got {tuple(values.shape)}")
        self._edit(optimizer, lambda n, t, is_state: (torch.zeros_like(t) if is_state else
                                                       values.detach().to(t.dtype))
                   if n == name else t)

    # -- geometry branch -------------------------------------------------------------------
    def shortest_axes(self) -> Tensor:
        """(N, 3) unit world direction of each Gaussian's smallest scale axis."""
        with torch.no_grad():
            R = quat_to_rotmat(self.params["quats"])
            axis = self.params["scales"].argmin(dim=1)
            return R[torch.arange(len(self), device=R.device), :, axis]

    def init_geometry(self, camera_centers: Tensor,
                      optimizer: torch.optim.Optimizer | None = None,
                      seen_from: Tensor | None = None) -> None:
        """Start of stage 2 (docs/design.md section 5): opacity_g becomes its own parameter, a copy of
        opacity_c; normals are the shortest axes, flipped to face the cameras: those that see
        the Gaussian when `seen_from` (N, 3) (sum of directions to them,
        core.render.seen_directions) is non-zero, else the mean direction to all `camera_centers`
        (K, 3), which around a subject filmed from all sides is nearly vertical and so decides
        the side of a flank by chance."""
        with torch.no_grad():
            axes = self.shortest_axes()
            to_cams = torch.nn.functional.normalize(
                camera_centers.float()[None, :, :] - self.means[:, None, :], dim=-1).mean(dim=1)
            if seen_from is not None:
                seen = seen_from.norm(dim=1, keepdim=True) > 1e-6
                to_cams = torch.where(seen, seen_from, to_cams)
            sign = torch.where((axes * to_cams).sum(dim=1, keepdim=True) < 0, -1.0, 1.0)
            self.assign("normals", axes * sign, optimizer)
            self.assign("opacity_g", self.params["opacity_c"].detach().clone(), optimizer)

    # -- files -----------------------------------------------------------------------------
    def save_ply(self, path) -> None:
        """Write the standard 3DGS layout plus opacity_geo, normal_x/y/z, visibility."""
        write_gaussian_ply(path, {k: v.detach().cpu() for k, v in self.params.items()})

    @classmethod
    def load_ply(cls, path, device: torch.device | str = "cpu") -> GaussianModel:
        """Read a file written by :meth:`save_ply`, or a plain 3DGS PLY (geometry defaults),
        onto `device`."""
        return cls({k: torch.from_numpy(v).to(device) for k, v in read_gaussian_ply(path).items()})
