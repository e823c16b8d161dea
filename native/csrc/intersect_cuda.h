// CUDA launchers of tile binning (intersect.cu). No torch here; see projection_cuda.h for the
// conventions (device pointers, asynchronous on `stream`, cudaError_t launch status).
//
// Binning needs the number of (Gaussian, tile) pairs M before it can allocate the sort buffers,
// so it runs in two phases, and each phase takes caller-provided scratch memory whose size it
// reports first (like CUB): the torch side allocates it as a byte tensor from the caching
// allocator.
//
//   size_t t1 = intersect_count_temp_bytes(n);
//   launch_intersect_count(rects, n, W, H, ts, cum_counts, temp1, t1, stream);
//   int64_t m = n > 0 ? cum_counts[n - 1] : 0;   // the one device-to-host copy (a sync)
//   size_t t2 = intersect_sort_temp_bytes(m, W, H, ts);
//   launch_intersect_sort(rects, depths, cum_counts, n, m, W, H, ts, tile_offsets, flat_ids,
//                         temp2, t2, stream);
//
// The result equals intersect.cpp: tile t's Gaussians are flat_ids[tile_offsets[t] :
// tile_offsets[t+1]], sorted by depth, ties by index. The sort key is 64 bits: tile id in the high
// 32, the depth as an order-preserving 32-bit pattern of the float in the low 32 (double depths
// are rounded to float for the key, so depths equal in float sort by index). CUB's radix sort is
// stable and the pairs are emitted in index order, which gives the index tie-break.
#pragma once

#include <cuda_runtime_api.h>

#include <cstddef>
#include <cstdint>

namespace dgs {
namespace cuda {

// Scratch bytes needed by launch_intersect_count for n Gaussians.
size_t intersect_count_temp_bytes(int64_t n);

// Phase 1. rects (n,4) int32 inclusive pixel boxes (empty when u0 > u1 or v0 > v1).
// Writes cum_counts (n) int64: the inclusive prefix sum of the number of tiles each box touches.
// tile_size > 0; width, height >= 0.
cudaError_t launch_intersect_count(const int32_t* rects, int64_t n, int width, int height,
                                   int tile_size, int64_t* cum_counts, void* temp,
                                   size_t temp_bytes, cudaStream_t stream);

// Scratch bytes needed by launch_intersect_sort for m pairs on this image and tile size.
size_t intersect_sort_temp_bytes(int64_t m, int width, int height, int tile_size);

// Phase 2. depths (n) float or double; cum_counts from phase 1; m = cum_counts[n-1] (0 if n == 0).
// Writes tile_offsets (n_tiles + 1) int64, n_tiles = ceil(W/ts) * ceil(H/ts), and flat_ids (m)
// int32. flat_ids may be null when m == 0.
template <typename T>
cudaError_t launch_intersect_sort(const int32_t* rects, const T* depths,
                                  const int64_t* cum_counts, int64_t n, int64_t m, int width,
                                  int height, int tile_size, int64_t* tile_offsets,
                                  int32_t* flat_ids, void* temp, size_t temp_bytes,
                                  cudaStream_t stream);

}  // namespace cuda
}  // namespace dgs
