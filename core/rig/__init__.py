"""Geometry from a calibrated rig: per-view depth by a plane sweep over the known poses, fused
across views with a consistency check; it seeds key frames densely and gives every training
view a normal prior where a capture has neither points nor priors (docs/design.md "Initial
points" and "Normal priors")."""

from core.rig.depth import rig_depth
from core.rig.fusion import Fused, backproject, fuse
from core.rig.stereo import DepthMap, choose_sources, depth_range, plane_sweep

__all__ = ["DepthMap", "Fused", "backproject", "choose_sources", "depth_range", "fuse",
           "plane_sweep", "rig_depth"]
