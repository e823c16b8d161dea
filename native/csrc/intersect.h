// Tile binning and depth sort: which Gaussians touch which 16x16 tile, front to back.
#pragma once

#include <ATen/ATen.h>

#include <tuple>

namespace dgs {

// rects (N,4) int32 inclusive pixel boxes (empty when u0 > u1), depths (N).
// Returns tile_offsets (n_tiles + 1) int64 and flat_ids (M) int32: the Gaussians of tile t are
// flat_ids[tile_offsets[t] : tile_offsets[t+1]], sorted by (depth, index).
std::tuple<at::Tensor, at::Tensor> intersect_tiles(const at::Tensor& rects,
                                                   const at::Tensor& depths, int64_t width,
                                                   int64_t height, int64_t tile_size);

#ifdef DGS_WITH_CUDA
// The same op on CUDA tensors (intersect_cuda.cpp); intersect_tiles calls it for CUDA inputs.
std::tuple<at::Tensor, at::Tensor> intersect_tiles_cuda(const at::Tensor& rects,
                                                        const at::Tensor& depths, int64_t width,
                                                        int64_t height, int64_t tile_size);
#endif

}  // namespace dgs
