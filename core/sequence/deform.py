"""The deform stage: the previous frame's Gaussians moved by the embedded deformation graph, whose
node rotations and translations are optimised against this frame's views with photometric +
normal + quaternion unit-norm + ARAP losses (docs/design.md section 5). Everything but positions,
rotations and normals stays as it was, so the Gaussians keep their identity (correspondence).

Fast motion (a limb moving by more than its width between frames) is outside the basin of a
sharp photometric loss; the first half of the stage therefore compares blurred images, the blur
shrinking to none (coarse to fine, as image-alignment methods since Lucas-Kanade do).
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor

from core.losses import blur
from core.model import GaussianModel
from core.sequence.graph import DeformationGraph, arap_loss, quat_norm_loss

__all__ = ["DeformedGaussians", "blur", "blur_sigma", "deform_losses"]


class DeformedGaussians:
    """A read-only view of `base` with deformed means, quaternions and normals (differentiable
    with respect to the graph's node parameters); `core.render.render` draws it like a model.
    With `rows` (indices) the graph moves those Gaussians (it was built on them) and the rest
    stay where they are."""

    def __init__(self, base: GaussianModel, graph: DeformationGraph, rotations: Tensor,
                 translations: Tensor, rows: Tensor | None = None):
        self.base = base
        p = base.params
        means, quats, normals = (p[k].detach() for k in ("means", "quats", "normals"))
        if rows is None:
            self._means, quats, normals = graph.deform(means, quats, normals, rotations,
                                                       translations)
        else:
            moved = graph.deform(means[rows], quats[rows], normals[rows], rotations,
                                 translations)
            self._means, quats, normals = (whole.index_put((rows,), part) for whole, part in
                                           zip((means, quats, normals), moved))
        self._quats = F.normalize(quats, dim=-1)
        self._normals = F.normalize(normals, dim=-1)
        self.raw_quats, self.raw_normals = quats, normals

    def __len__(self) -> int:
        return len(self.base)

    means = property(lambda self: self._means)
    quats = property(lambda self: self._quats)
    normals = property(lambda self: self._normals)
    scales = property(lambda self: self.base.scales.detach())
    opacity_c = property(lambda self: self.base.opacity_c.detach())
    opacity_g = property(lambda self: self.base.opacity_g.detach())
    visibility = property(lambda self: self.base.visibility.detach())
    sh = property(lambda self: self.base.sh.detach())

    def to_model(self) -> GaussianModel:
        """A new model: the base's parameters with the deformed ones (raw quaternions and
        normals keep their norms' role: the model normalises them)."""
        params = {k: v.detach() for k, v in self.base.params.items()}
        params.update(means=self._means.detach(), quats=self.raw_quats.detach(),
                      normals=self.raw_normals.detach())
        return GaussianModel(params)


def blur_sigma(step: int, steps: int, sigma0: float) -> float:
    """The coarse-to-fine blur at `step` of `steps`: sigma0 at 0, linearly 0 by steps / 2."""
    half = max(steps / 2, 1)
    return max(0.0, sigma0 * (1 - step / half))


def deform_losses(graph: DeformationGraph, rotations: Tensor, translations: Tensor, *,
                  arap: float = 1.0, quat_norm: float = 1.0) -> dict[str, Tensor]:
    """The graph's regularisers: weighted ARAP and node-quaternion unit norm."""
    return {"arap": arap * arap_loss(graph, rotations, translations),
            "quat_norm": quat_norm * quat_norm_loss(rotations)}
