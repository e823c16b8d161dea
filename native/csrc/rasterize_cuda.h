// CUDA launchers of the two-branch blending op (rasterize.cu). No torch here; see
// projection_cuda.h for the conventions (device pointers to contiguous row-major arrays,
// asynchronous on `stream`, cudaError_t launch status). The many arguments travel in a plain
// struct of raw pointers and sizes; shapes and meanings are those of rasterize.h.
//
// Limits (checked; the launchers return cudaErrorInvalidValue instead of computing garbage):
// 1 <= tile_size <= 16 (one thread per pixel of a tile, 256 threads at most); C >= 0, G >= 0 of
// any size (C = 3 with G in {0, 1, 3, 4, 5} keeps the per-pixel features in registers; every other
// combination runs a generic path that loops over channels in global memory); G must be 0 when
// geometry_branch is false; n < 2^31 (Gaussian ids are int32).
// T is float or double (double always takes the generic channel path; it is for gradcheck).
#pragma once

#include <cuda_runtime_api.h>

#include <cstdint>

namespace dgs {
namespace cuda {

template <typename T> struct RasterizeFwdParams {
  // Inputs, from projection and intersect.
  const T* means2d;              // (n, 2)
  const T* conics;               // (n, 3) [a, b, c] of [[a, b], [b, c]]
  const T* opacities;            // (n, 2) mixed [appearance, geometry]
  const T* depths;               // (n)
  const T* colors;               // (n, C)
  const T* geometry;             // (n, G); may be null when G == 0
  const int32_t* rects;          // (n, 4) inclusive pixel boxes
  const int64_t* tile_offsets;   // (n_tiles + 1)
  const int32_t* flat_ids;       // (m); may be null when m == 0
  int64_t n;
  int C, G, width, height, tile_size;
  bool geometry_branch;  // false: appearance only
  // Outputs. Every pixel entry is written (no zero-filling needed by the caller).
  T* out_color;       // (H, W, C)
  T* out_geometry;    // (H, W, G); may be null when G == 0
  T* out_depth;       // (H, W, 1)  sum of z * alpha_g * T_g
  T* transmittance;   // (H, W, 2)  final T per branch (1 for a branch that is off)
  int32_t* stops;     // (H, W, 2)  per branch, tile-list position where the branch stopped, or
                      //            the list length (0 for a branch that is off)
  T* contribution;    // (n) max over pixels of alpha * T in either branch; zero-filled by the
                      //     launcher, then raised with atomicMax
};

template <typename T> struct RasterizeBwdParams {
  // The forward's inputs (same meaning as RasterizeFwdParams).
  const T *means2d, *conics, *opacities, *depths, *colors, *geometry;
  const int32_t* rects;
  const int64_t* tile_offsets;
  const int32_t* flat_ids;
  int64_t n;
  int C, G, width, height, tile_size;
  bool geometry_branch;
  // The forward's outputs, saved.
  const T* out_color;      // (H, W, C)
  const T* out_geometry;   // (H, W, G)
  const T* out_depth;      // (H, W, 1)
  const T* transmittance;  // (H, W, 2)
  const int32_t* stops;    // (H, W, 2)
  // Upstream gradients.
  const T* v_color;     // (H, W, C)
  const T* v_geometry;  // (H, W, G)
  const T* v_depth;     // (H, W, 1)
  const T* v_alpha;     // (H, W, 2) of alpha = 1 - transmittance, per branch
  // Gradients, zero-filled by the launcher and accumulated with warp-reduced atomicAdd.
  T* g_means2d;    // (n, 2)
  T* g_conics;     // (n, 3)
  T* g_opacities;  // (n, 2)
  T* g_depths;     // (n)
  T* g_colors;     // (n, C)
  T* g_geometry;   // (n, G)
  T* absgrad;      // (n, 4) AbsGS sums of |dL/dmean2d| per pixel: appearance (x, y), geometry
                   //        (x, y). Overwritten, not added to: the caller adds them to its
                   //        running statistics, as the CPU op's caller does.
};

template <typename T>
cudaError_t launch_rasterize_fwd(const RasterizeFwdParams<T>& p, cudaStream_t stream);

template <typename T>
cudaError_t launch_rasterize_bwd(const RasterizeBwdParams<T>& p, cudaStream_t stream);

}  // namespace cuda
}  // namespace dgs
