// Blending of both branches in one pass: appearance features with the appearance alpha,
// geometry features and depth with the geometry alpha (DESIGN.md 3.4). With geometry_branch
// false only the appearance branch runs (a plain single-opacity RGB pass; G must then be 0).
#pragma once

#include <ATen/ATen.h>

#include <tuple>

namespace dgs {

// Returns color (H,W,C), geometry (H,W,G), depth (H,W,1), transmittance (H,W,2) [appearance,
// geometry], stops (H,W,2) int32 (per branch, the position in the tile list where the branch
// stopped, or the list length), contribution (N) = max over pixels of alpha * T in either branch.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
rasterize_fwd(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
              const at::Tensor& depths, const at::Tensor& colors, const at::Tensor& geometry,
              const at::Tensor& rects, const at::Tensor& tile_offsets, const at::Tensor& flat_ids,
              int64_t width, int64_t height, int64_t tile_size, bool geometry_branch);

// Returns gradients for means2d (N,2), conics (N,3), opacities (N,2), depths (N), colors (N,C),
// geometry (N,G), and the AbsGS sums (N,4): |dL/dmean2d| per pixel summed, appearance (x, y)
// then geometry (x, y).
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
rasterize_bwd(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
              const at::Tensor& depths, const at::Tensor& colors, const at::Tensor& geometry,
              const at::Tensor& rects, const at::Tensor& tile_offsets, const at::Tensor& flat_ids,
              int64_t width, int64_t height, int64_t tile_size, bool geometry_branch,
              const at::Tensor& out_color, const at::Tensor& out_geometry,
              const at::Tensor& out_depth, const at::Tensor& transmittance,
              const at::Tensor& stops, const at::Tensor& v_color, const at::Tensor& v_geometry,
              const at::Tensor& v_depth, const at::Tensor& v_alpha);

#ifdef DGS_WITH_CUDA
// The same ops on CUDA tensors (rasterize_cuda.cpp); the functions above call them for CUDA
// inputs.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
rasterize_fwd_cuda(const at::Tensor& means2d, const at::Tensor& conics,
                   const at::Tensor& opacities, const at::Tensor& depths,
                   const at::Tensor& colors, const at::Tensor& geometry, const at::Tensor& rects,
                   const at::Tensor& tile_offsets, const at::Tensor& flat_ids, int64_t width,
                   int64_t height, int64_t tile_size, bool geometry_branch);

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
rasterize_bwd_cuda(const at::Tensor& means2d, const at::Tensor& conics,
                   const at::Tensor& opacities, const at::Tensor& depths,
                   const at::Tensor& colors, const at::Tensor& geometry, const at::Tensor& rects,
                   const at::Tensor& tile_offsets, const at::Tensor& flat_ids, int64_t width,
                   int64_t height, int64_t tile_size, bool geometry_branch,
                   const at::Tensor& out_color, const at::Tensor& out_geometry,
                   const at::Tensor& out_depth, const at::Tensor& transmittance,
                   const at::Tensor& stops, const at::Tensor& v_color,
                   const at::Tensor& v_geometry, const at::Tensor& v_depth,
                   const at::Tensor& v_alpha);
#endif

}  // namespace dgs
