"""Densification and pruning for disentangled Gaussians (docs/design.md section 5), as a strategy
object with explicit state, in the manner of gsplat's `strategy/` (called after each step).

- Statistics: AbsGS (Ye et al. 2024) per branch, the mean over the views that saw a Gaussian of
  the norm of its per-view absolute screen-space gradient, in NDC units (pixel gradients times
  W/2, H/2, as 3DGS and gsplat measure them); or (`gradient` mean) 3DGS's, the norm of the
  per-view screen-space gradient itself.
- A Gaussian is densified when either branch passes its threshold. Small ones are cloned, large
  ones split in two (3DGS: scale threshold percent_dense 0.01 x scene extent, split samples drawn
  from the Gaussian, scales divided by 1.6). In a branch that passed, both resulting Gaussians get
  opacity 1 - sqrt(1 - o) (Bulo et al. 2024, "Revising densification in Gaussian splatting"),
  so that together they cover like the original (`revised_opacity`; off, both keep o as in
  3DGS); in a branch that did not pass, the original (or first sample) keeps its opacity and
  the copy starts at 0.005.
- At each opacity reset: drop the rho fraction with the lowest contribution (max over views of
  alpha*T in either branch since the last reset) and those transparent in both branches; then
  rho *= 0.75 and opacities become min(o, 0.01) (3DGS reset; `reset_opacity` off leaves them,
  as released gsplat 1.5.3 does). With `prune_at` densify the transparent ones go at every
  densification instead, as in 3DGS.
- With `relocate` the transparent are moved instead (3DGS-MCMC, Kheradmand et al. 2024): at each
  densification each takes the place of a copy of a live Gaussian drawn by opacity, and the
  drawn one and its copies share its cover (`relocation`, the paper's Eq. 9).
- From the first reset on, every densification and reset also drops Gaussians whose largest scale
  exceeds 0.1 x the scene extent (3DGS densify_and_prune `big_points_ws`; gsplat
  DefaultStrategy prune_scale3d 0.1): a sheet that large is a floater the training views cannot
  see (e.g. dark against a dark background), not part of the subject.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from core.config import DensifyConfig
from core.model import GaussianModel
from native.reference import quat_to_rotmat
from native.types import RasterOutput

__all__ = ["MAX_COPIES", "DensifyStrategy", "StrategyState", "relocation"]


MAX_COPIES = 51
"""At most this many Gaussians share one relocated Gaussian's cover (gsplat's n_max)."""
_LINE = torch.linspace(-10.0, 10.0, 801, dtype=torch.float64)
"""Where `relocation` integrates a unit Gaussian's alpha along a line through its centre."""


def _shared_opacity(opacity: Tensor, copies: Tensor) -> Tensor:
    """The opacity o' each of `copies` Gaussians at one place takes to keep `opacity` at the
    centre: 1 - (1 - o')^n = o (`copies` clamped to `MAX_COPIES`, as in `relocation`)."""
    n = copies.clamp(max=MAX_COPIES).to(torch.float64)
    o = opacity.to(torch.float64).clamp(0.0, 1.0 - 1e-12)
    return 1.0 - (1.0 - o) ** (1.0 / n)


def relocation(opacity: Tensor, scales: Tensor, copies: Tensor) -> tuple[Tensor, Tensor]:
    """3DGS-MCMC's Eq. 9: the opacity (N,) and scales (N, 3) that each of `copies` (N,) >= 1
    Gaussians at one place takes so that together they keep the original's (`opacity`,
    `scales`): its opacity at the centre, 1 - (1 - o')^n = o, and the integral of its alpha
    along a line through the centre, s o = s' sum_j C(n, j) (-1)^(j+1) o'^j / sqrt(j). The
    alternating sum loses every digit to cancellation for large n and o' (its terms reach
    1e13), so the same integral is evaluated by quadrature of the positive integrand
    1 - (1 - o' exp(-x^2 / 2))^n (a trapezoid rule, float64: exact to ~1e-12). `copies` is
    clamped to `MAX_COPIES`."""
    if opacity.dim() != 1 or scales.shape != (opacity.shape[0], 3) or \
            copies.shape != opacity.shape:
        raise ValueError(f"opacity (N,), scales (N, 3), copies (N,): got {tuple(opacity.shape)}"
                         f", {tuple(scales.shape)}, {tuple(copies.shape)}")
    if bool((copies < 1).any()):
        raise ValueError("copies: expected >= 1")
    n = copies.clamp(max=MAX_COPIES).to(torch.float64)
    o = opacity.to(torch.float64).clamp(0.0, 1.0 - 1e-12)
    shared = _shared_opacity(o, n)
    line = _LINE.to(o.device)
    denom = torch.empty_like(o)
    for start in range(0, o.shape[0], 4096):  # (rows, 801) at a time
        part = slice(start, start + 4096)
        alpha = 1.0 - (1.0 - shared[part, None] * torch.exp(-0.5 * line * line)) ** n[part, None]
        denom[part] = torch.trapezoid(alpha, line, dim=1) / math.sqrt(2.0 * math.pi)
    coeff = torch.where(denom > 0, o / denom.clamp_min(1e-300), torch.ones_like(o))
    return shared.to(opacity.dtype), scales * coeff.to(scales.dtype)[:, None]


@dataclass
class StrategyState:
    """Per-Gaussian statistics since the last densification (gradients, counts, radii) or the last
    reset (contribution), and the current pruning fraction."""

    grad_c: Tensor
    """(N,) summed AbsGS gradient norms of the appearance branch."""
    grad_g: Tensor
    """(N,) summed AbsGS gradient norms of the geometry branch."""
    count: Tensor
    """(N,) number of views in which the Gaussian was drawn."""
    max_radii: Tensor
    """(N,) largest screen radius seen (pixels)."""
    contribution: Tensor
    """(N,) max over views of alpha * T in either branch."""
    rho: float
    """Fraction pruned by lowest contribution at the next reset."""
    resets: int = 0
    """Opacity resets done so far."""
    history: list[dict[str, int]] = field(default_factory=list)
    """One record per densification / reset: counts cloned, split, pruned."""
    frozen: Tensor | None = None
    """(N,) bool: Gaussians never densified or pruned (a tracked frame's static scene); None:
    none. New rows inherit their parent's."""

    def select(self, index: Tensor) -> None:
        """Re-index every per-Gaussian tensor (a boolean mask or an index tensor)."""
        for name in ("grad_c", "grad_g", "count", "max_radii", "contribution"):
            setattr(self, name, getattr(self, name)[index])
        if self.frozen is not None:
            self.frozen = self.frozen[index]


class DensifyStrategy:
    """Grow, prune and reset a GaussianModel together with its optimizer's state."""

    def __init__(self, config: DensifyConfig = DensifyConfig(), extent: float = 1.0):
        if not extent > 0:
            raise ValueError(f"extent: expected a positive scene extent, got {extent}")
        self.config = config
        self.extent = float(extent)
        self._ndc_cache: dict[tuple, Tensor] = {}

    def initialize_state(self, n: int, device: torch.device | str = "cpu") -> StrategyState:
        """Zero statistics for `n` Gaussians, on `device` (the model's)."""
        z = torch.zeros(n, device=device)
        return StrategyState(z.clone(), z.clone(), z.clone(), z.clone(), z.clone(),
                             rho=self.config.rho)

    def update(self, state: StrategyState, out: RasterOutput, width: int, height: int) -> None:
        """Accumulate one view's statistics (call after backward, which fills the absgrads)."""
        n = state.count.shape[0]
        if out.radii.shape[0] != n:
            raise ValueError(f"out: rendered {out.radii.shape[0]} Gaussians, state has {n}")
        with torch.no_grad():
            ndc = self._ndc(width, height, state.count.device)
            seen = out.radii > 0
            if self.config.gradient == "absolute":
                state.grad_c += torch.where(seen, (out.absgrad_c.detach() * ndc).norm(dim=1), 0)
                state.grad_g += torch.where(seen, (out.absgrad_g.detach() * ndc).norm(dim=1), 0)
            elif out.means2d.grad is not None:  # both branches' gradient, in grad_c
                state.grad_c += torch.where(seen, (out.means2d.grad * ndc).norm(dim=1), 0)
            state.count += seen.float()
            state.max_radii = torch.maximum(state.max_radii, out.radii.float())
            state.contribution = torch.maximum(state.contribution, out.contribution.detach())

    def _ndc(self, width: int, height: int, device: torch.device) -> Tensor:
        """(2,) half the image size, made once per camera size and device: a tensor built from
        host numbers is a host-to-device copy, which on a GPU waits for the queued steps."""
        key = (width, height, str(device))
        if key not in self._ndc_cache:
            self._ndc_cache[key] = torch.tensor([width / 2.0, height / 2.0], device=device)
        return self._ndc_cache[key]

    def _selection(self, model: GaussianModel, state: StrategyState) -> tuple[Tensor, Tensor]:
        """Which Gaussians passed in the appearance / geometry branch (capped growth)."""
        cfg = self.config
        denom = state.count.clamp_min(1)
        pass_c = state.grad_c / denom > cfg.grad_threshold_c
        pass_g = state.grad_g / denom > cfg.grad_threshold_g
        if cfg.max_gaussians is not None:
            room = max(cfg.max_gaussians - len(model), 0)
            score = torch.maximum(state.grad_c / cfg.grad_threshold_c,
                                  state.grad_g / cfg.grad_threshold_g) / denom
            score = torch.where(pass_c | pass_g, score, -1.0)
            over = score.argsort(descending=True)[room:]
            pass_c[over] = False
            pass_g[over] = False
        return pass_c, pass_g

    def densify(self, model: GaussianModel, optimizer: torch.optim.Optimizer | None,
                state: StrategyState, generator: torch.Generator | None = None,
                tied: bool = False) -> dict[str, int]:
        """Clone / split where either branch passed its threshold; reset the gradient stats;
        prune those too big (after the first reset) and, with `prune_at` densify, the
        transparent (`tied` as in `prune_and_reset`). `state.frozen` rows are left alone."""
        prune_faint = self.config.prune_at == "densify" and not self.config.relocate
        with torch.no_grad():
            pass_c, pass_g = self._selection(model, state)
            if state.frozen is not None:
                pass_c, pass_g = pass_c & ~state.frozen, pass_g & ~state.frozen
            selected = pass_c | pass_g
            small = model.scales.max(dim=1).values <= self.config.clone_scale * self.extent
            clone, split = selected & small, selected & ~small
            if bool(selected.any()):
                n = len(model)
                new_c = self._clone(model, clone, pass_c, pass_g)
                new_s = self._split(model, split, pass_c, pass_g, generator)
                model.extend({k: torch.cat([new_c[k], new_s[k]]) for k in new_c}, optimizer)
                # New rows inherit their parent's statistics (the contribution matters).
                parents = torch.cat([clone.nonzero()[:, 0], split.nonzero()[:, 0].repeat(2)])
                state.select(torch.cat([torch.arange(n, device=parents.device), parents]))
                keep = torch.ones(len(model), dtype=torch.bool, device=model.device)
                keep[:n] = ~split
                model.keep(keep, optimizer)
                state.select(keep)
            for name in ("grad_c", "grad_g", "count", "max_radii"):
                getattr(state, name).zero_()
            moved = self._relocate(model, optimizer, state, generator, tied) \
                if self.config.relocate else 0
            big = self._too_big(model, state)
            faint = self._transparent(model, tied) if prune_faint else torch.zeros_like(big)
            drop = big | faint
            if state.frozen is not None:
                drop &= ~state.frozen
            if bool(drop.all()):
                drop[:] = False  # never leave an empty model
            if bool(drop.any()):
                model.keep(~drop, optimizer)
                state.select(~drop)
        record = {"cloned": int(clone.sum()), "split": int(split.sum()),
                  "pruned_big": int((big & drop).sum()), "n": len(model)}
        if prune_faint:
            record["pruned"] = int((faint & drop).sum())
        if self.config.relocate:
            record["relocated"] = moved
        state.history.append(record)
        return record

    def _relocate(self, model: GaussianModel, optimizer: torch.optim.Optimizer | None,
                  state: StrategyState, generator: torch.Generator | None, tied: bool) -> int:
        """Move the transparent (`_transparent`, never `state.frozen` rows) onto live ones
        drawn with replacement by opacity (the larger branch's; the appearance one's when
        `tied`): each drawn Gaussian and its copies take `relocation`'s opacities (per branch,
        at least `transparent`) and scales (from the appearance opacity, what the picture
        shows); the moved rows inherit the drawn one's statistics, and both have their Adam
        moments zeroed. Returns how many moved."""
        cfg = self.config
        dead = self._transparent(model, tied)
        live = ~dead
        if state.frozen is not None:
            dead, live = dead & ~state.frozen, live & ~state.frozen
        o_c, o_g = model.opacity_c.detach(), model.opacity_g.detach()
        weight = (o_c if tied else torch.maximum(o_c, o_g))[live]
        count = int(dead.sum())
        if count == 0 or not bool((weight > 0).any()):
            return 0
        live_idx, dead_idx = live.nonzero()[:, 0], dead.nonzero()[:, 0]
        # Drawn on the (CPU) generator whatever the device, the same draws everywhere; by the
        # inverse of the cumulative weight (torch.multinomial stops at 2^24 categories).
        cdf = torch.cumsum(weight.double().cpu(), dim=0)
        u = torch.rand(count, generator=generator, dtype=torch.float64) * cdf[-1]
        draw = torch.searchsorted(cdf, u, right=True).clamp(max=cdf.numel() - 1)
        draw = draw.to(live_idx.device)
        sources = live_idx[draw]
        copies = torch.bincount(sources, minlength=len(model))
        picked = copies.nonzero()[:, 0]
        n = copies[picked] + 1
        rows = {k: p.detach()[picked].clone() for k, p in model.params.items()}
        shared_c, scales_new = relocation(o_c[picked], model.scales.detach()[picked], n)
        shared_g = _shared_opacity(o_g[picked], n).to(o_g.dtype)  # the scale is shared
        floor, top = cfg.transparent, 1.0 - 1e-6
        rows["opacity_c"] = torch.logit(shared_c.clamp(floor, top))
        rows["opacity_g"] = torch.logit(shared_g.clamp(floor, top))
        rows["scales"] = torch.log(scales_new)
        where = torch.searchsorted(picked, sources)  # each moved row's source among `picked`
        model.replace_rows(torch.cat([picked, dead_idx]),
                           {k: torch.cat([v, v[where]]) for k, v in rows.items()}, optimizer)
        index = torch.arange(len(model), device=sources.device)
        index[dead_idx] = sources
        state.select(index)
        return count

    def _too_big(self, model: GaussianModel, state: StrategyState) -> Tensor:
        """(N,) Gaussians larger than prune_scale x extent, once a reset has happened (before it
        the initial points may still be large)."""
        if self.config.prune_scale is None or state.resets == 0:
            return torch.zeros(len(model), dtype=torch.bool, device=model.device)
        return model.scales.max(dim=1).values > self.config.prune_scale * self.extent

    def _transparent(self, model: GaussianModel, tied: bool) -> Tensor:
        """(N,) below `transparent` in both branches (in the appearance one when `tied`)."""
        o_c = model.opacity_c
        o_g = o_c if tied else model.opacity_g
        return (o_c < self.config.transparent) & (o_g < self.config.transparent)

    @staticmethod
    def _branch_opacities(raw: Tensor, passed: Tensor, cfg: DensifyConfig) -> tuple[Tensor, Tensor]:
        """(kept, copy) opacity logits for one branch: where it passed, both Bulo's
        (`revised_opacity`) or both the original's; elsewhere (o, 0.005)."""
        if cfg.revised_opacity:
            shared = torch.logit(1 - torch.sqrt(1 - torch.sigmoid(raw)), eps=1e-6)
        else:
            shared = raw
        copy = torch.where(passed, shared, math.log(cfg.new_branch_opacity
                                                    / (1 - cfg.new_branch_opacity)))
        return torch.where(passed, shared, raw), copy

    def _clone(self, model: GaussianModel, mask: Tensor, pass_c: Tensor,
               pass_g: Tensor) -> dict[str, Tensor]:
        rows = {k: p.detach()[mask].clone() for k, p in model.params.items()}
        for name, passed in (("opacity_c", pass_c[mask]), ("opacity_g", pass_g[mask])):
            kept, copy = self._branch_opacities(rows[name], passed, self.config)
            model.params[name].data[mask] = kept
            rows[name] = copy
        return rows

    def _split(self, model: GaussianModel, mask: Tensor, pass_c: Tensor, pass_g: Tensor,
               generator: torch.Generator | None) -> dict[str, Tensor]:
        """Two samples per split Gaussian: first all the first samples, then all the second."""
        rows = {k: p.detach()[mask] for k, p in model.params.items()}
        scales = torch.exp(rows["scales"])
        R = quat_to_rotmat(rows["quats"])
        out = {k: v.repeat((2,) + (1,) * (v.dim() - 1)) for k, v in rows.items()}
        # Drawn on the (CPU) generator whatever the device: the same samples everywhere.
        noise = torch.randn(2 * scales.shape[0], 3, generator=generator).to(scales.device) \
            * scales.repeat(2, 1)
        out["means"] = out["means"] + torch.einsum("nij,nj->ni", R.repeat(2, 1, 1), noise)
        out["scales"] = torch.log(scales / self.config.split_factor).repeat(2, 1)
        for name, passed in (("opacity_c", pass_c[mask]), ("opacity_g", pass_g[mask])):
            kept, copy = self._branch_opacities(rows[name], passed, self.config)
            out[name] = torch.cat([kept, copy])
        return out

    def prune_and_reset(self, model: GaussianModel, optimizer: torch.optim.Optimizer | None,
                        state: StrategyState, tied: bool = False) -> dict[str, int]:
        """Prune (lowest-contribution fraction rho, transparent in both branches), decay rho,
        reset both opacities to min(o, reset_value) (unless `reset_opacity` is off). `tied`:
        opacity_g follows opacity_c (stage 1), so transparency is judged on opacity_c alone."""
        cfg = self.config
        with torch.no_grad():
            n = len(model)
            drop = self._too_big(model, state)
            if cfg.prune_at == "reset" and not cfg.relocate:
                drop |= self._transparent(model, tied)
            k = int(math.floor(state.rho * n))
            if k > 0:
                drop[state.contribution.argsort(stable=True)[:k]] = True
            if bool(drop.all()):
                drop[state.contribution.argmax()] = False  # never leave an empty model
            model.keep(~drop, optimizer)
            state.select(~drop)
            if cfg.reset_opacity:
                limit = math.log(cfg.reset_value / (1 - cfg.reset_value))
                for name in ("opacity_c", "opacity_g"):
                    model.assign(name, model.params[name].detach().clamp_max(limit), optimizer)
            state.contribution.zero_()
            record = {"pruned": int(drop.sum()), "n": len(model), "rho_percent": round(
                100 * state.rho)}
            state.rho *= cfg.rho_decay
            state.resets += 1
        state.history.append(record)
        return record
