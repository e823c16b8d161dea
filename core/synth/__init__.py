"""Synthetic captures with ground truth: an articulated figure, a CPU rasterizer, SH lighting
(the ground-truth meshes are PLY files of `core.plyio`)."""

from core.synth.figure import Figure, FigureMesh
from core.synth.generate import SynthConfig, degrade_normals, dome_cameras, synthesize
from core.synth.raster import Fragments, interpolate, rasterize, rasterize_perspective

__all__ = [
    "Figure",
    "FigureMesh",
    "Fragments",
    "SynthConfig",
    "degrade_normals",
    "dome_cameras",
    "interpolate",
    "rasterize",
    "rasterize_perspective",
    "synthesize",
]
