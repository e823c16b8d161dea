"""Synthetic captures with ground truth: an articulated figure, a CPU rasterizer, SH lighting."""

from core.synth.figure import Figure, FigureMesh
from core.synth.generate import SynthConfig, degrade_normals, dome_cameras, synthesize
from core.synth.ply import read_ply, write_ply
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
    "read_ply",
    "synthesize",
    "write_ply",
]
