"""The differentiable disentangled rasterizer and the Gaussian ray tracer for ambient occlusion
(C++ kernels for the CPU, CUDA kernels compiled in where a GPU and nvcc are found), with their
plain PyTorch references.

Importing this package never builds the extension; the first native call does (see _backend).
"""

from native._backend import NativeBuildError
from native.rasterize import Backend, rasterize
from native.raytrace import gaussian_rays, gaussian_visibility, trace_visibility
from native.types import RasterOutput

__all__ = ["rasterize", "RasterOutput", "NativeBuildError", "Backend", "trace_visibility",
           "gaussian_rays", "gaussian_visibility"]
