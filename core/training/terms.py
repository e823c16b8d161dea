"""The image loss terms of one rendered view, assembled once for every kind of frame: a key
frame's step (`core.training.keyframe.Trainer`) and a tracked frame's deform and refine steps
(`core.sequence.tracker.FrameTracker`). The stage plan says which terms are on; what differs
between the frame kinds is an argument, not a second copy:

- `blur_sigma`: the deform stage compares blurred images (coarse to fine);
- `mask_term`: the geometry mask loss (key frames: on; tracked frames: `sequence.geometry_mask`);
- `ao_target`: the visibility term needs baked AO maps (a key frame's stage 3; a tracked frame's
  refine stage only with `sequence.bake_ao`).
"""

from __future__ import annotations

from torch import Tensor

from core.config import LossWeights
from core.losses import (
    blur,
    depth_normal_consistency,
    geometry_mask_loss,
    normal_prior_loss,
    photometric_loss,
    visibility_loss,
)
from core.stages import StagePlan

__all__ = ["image_terms"]


def image_terms(r, view, camera, target: Tensor, plan: StagePlan, weights: LossWeights, *,
                blur_sigma: float = 0.0, mask_term: bool = True,
                ao_target: Tensor | None = None) -> dict[str, Tensor]:
    """{term: weighted loss} of render `r` (`core.render.Render`) of training `view`
    (`core.training.View`) by `camera` (`core.render.RenderCamera`) against `target` (the
    picture on this step's background), with the terms `plan` turns on (module docstring)."""
    terms = {"photometric": photometric_loss(blur(r.rgb, blur_sigma), blur(target, blur_sigma),
                                             weights)}
    if plan.normal_prior and view.normal is not None:
        terms["normal"] = normal_prior_loss(r.normal, view.normal, view.mask, weights,
                                            view.normal_weight, view.normal_measured)
    if mask_term and plan.geometry_branch and not plan.tie_opacity and view.mask is not None \
            and weights.geometry_mask > 0:
        terms["mask"] = geometry_mask_loss(r.alpha_g, view.mask, weights)
    if plan.consistency:
        terms["consistency"] = depth_normal_consistency(r.normal, r.depth, r.alpha_g, camera.K,
                                                        camera.viewmat, weights)
    if plan.visibility and ao_target is not None:
        terms["visibility"] = visibility_loss(r.visibility, ao_target, view.mask, weights,
                                              view.normal)
    return terms
