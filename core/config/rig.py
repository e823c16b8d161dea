"""How a calibrated rig gives a key frame dense seeds and normal priors without a point cloud or
a normal estimator (`core.rig`, docs/design.md "Initial points" and "Normal priors")."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from core.config.base import Fraction, section

__all__ = ["StereoConfig"]

Degrees = Annotated[float, Field(ge=0, le=180)]


@section
class StereoConfig:
    """Per-view depth by a plane sweep over the known poses, fused across views."""

    sources: Annotated[int, Field(ge=1, le=16)] = 4
    """Neighbouring cameras each view is matched with (chosen by baseline and angle)."""
    best: Annotated[int, Field(ge=1, le=16)] = 2
    """A depth's cost is the mean of its best this many sources' (a surface hidden from some
    neighbours still matches in the others)."""
    min_angle: Degrees = 3.0
    """Smallest angle (degrees) between a view's and a source's rays at the view's scene
    depth: below it depth is ill-posed."""
    max_angle: Degrees = 45.0
    """Largest such angle: above it the pictures differ too much to match."""
    target_angle: Degrees = 15.0
    """Sources whose angle is nearest this are preferred."""
    planes: Annotated[int, Field(ge=16, le=1024)] = 128
    """Most depth hypotheses, evenly spaced in inverse depth over the view's range: as many as
    move the view's central ray by about a pixel in its sources, up to this."""
    window: Annotated[int, Field(ge=3, le=31)] = 11
    """Side (pixels, odd) of the window the normalised cross-correlation compares."""
    max_side: Annotated[int, Field(ge=32, le=4096)] = 480
    """Views are matched reduced so their longer side is at most this many pixels."""
    max_cost: Fraction = 0.4
    """A depth is kept when its cost (1 - NCC, averaged over the best sources) is below this."""
    min_texture: Annotated[float, Field(ge=0, le=1)] = 0.002
    """... and the window's intensity standard deviation is at least this (flat: no match)."""
    min_views: Annotated[int, Field(ge=1, le=64)] = 2
    """Fusion: a pixel's point survives when at least this many other views' depths agree."""
    depth_tolerance: Annotated[float, Field(gt=0, le=1)] = 0.01
    """Fusion: views agree when their depths differ by at most this fraction."""
    reprojection: Annotated[float, Field(gt=0, le=100)] = 1.0
    """Fusion: ... and the other view's point reprojects within this many pixels."""
    normal_radius: Annotated[int, Field(ge=1, le=32)] = 6
    """Normal priors: the plane fitted to the fused depth spans (2 r + 1)^2 pixels."""
