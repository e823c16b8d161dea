"""The differentiable disentangled rasterizer (C++ CPU now, CUDA later) and its reference.

Importing this package never builds the extension; the first native call does (see _backend).
"""

from native._backend import NativeBuildError
from native.rasterize import Backend, rasterize
from native.types import RasterOutput

__all__ = ["rasterize", "RasterOutput", "NativeBuildError", "Backend"]
