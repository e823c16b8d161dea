// The extension module: it only registers the ops.
#include <torch/extension.h>

#include "intersect.h"
#include "projection.h"
#include "rasterize.h"
#include "raytrace.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("projection_fwd", &dgs::projection_fwd, "Project Gaussians (forward)");
  m.def("projection_bwd", &dgs::projection_bwd, "Project Gaussians (backward)");
  m.def("intersect_tiles", &dgs::intersect_tiles, "Bin Gaussians into tiles, sorted by depth");
  m.def("rasterize_fwd", &dgs::rasterize_fwd, "Blend both branches (forward)");
  m.def("rasterize_bwd", &dgs::rasterize_bwd, "Blend both branches (backward)");
#ifdef DGS_WITH_CUDA
  m.def("has_cuda", [] { return true; }, "Whether this build runs CUDA tensors");
#else
  m.def("has_cuda", [] { return false; }, "Whether this build runs CUDA tensors");
#endif
  m.def("trace_visibility", &dgs::trace_visibility, "Ambient occlusion by Gaussian ray tracing");
}
