// CUDA launchers of the projection op (projection.cu). No torch here: raw device pointers, sizes
// and a stream, so projection.cu compiles without a CUDA build of torch and projection.cpp can
// include this header with the host compiler under DGS_WITH_CUDA.
//
// Contract shared by both launchers:
// - Every pointer is a device pointer to a contiguous row-major array on the device of `stream`;
//   shapes are those of projection.h (N = n). viewmat (4,4) and K (3,3) are read on the device
//   (no host copy, no synchronization).
// - T is float or double (double is for gradcheck; production runs float).
// - Asynchronous on `stream`; the return value is the launch status (cudaSuccess, or
//   cudaErrorInvalidValue for a negative n or size). n == 0 launches nothing and succeeds.
// - Results equal the CPU kernel of projection.cpp (same culling, same zeros for culled
//   Gaussians) up to float rounding (nvcc contracts a*b+c into FMA).
#pragma once

#include <cuda_runtime_api.h>

#include <cstdint>

namespace dgs {
namespace cuda {

// Forward. Writes every output entry (no zero-filling needed by the caller):
// means2d (n,2), conics (n,3), depths (n), opacities (n,2) [appearance, geometry], rects (n,4)
// int32 inclusive pixel box (0, 0, -1, -1 when not drawn), radii (n) int32 (0 = not drawn).
template <typename T>
cudaError_t launch_projection_fwd(const T* means, const T* quats, const T* scales,
                                  const T* opacity_c, const T* opacity_g, const T* viewmat,
                                  const T* K, int64_t n, int width, int height, T beta, T eps2d,
                                  bool antialiased, T near_plane, T far_plane, T* means2d,
                                  T* conics, T* depths, T* opacities, int32_t* rects,
                                  int32_t* radii, cudaStream_t stream);

// Backward. Inputs as the forward plus the upstream gradients v_means2d (n,2), v_conics (n,3),
// v_depths (n), v_opacities (n,2). Writes every entry of g_means (n,3), g_quats (n,4),
// g_scales (n,3), g_opacity_c (n), g_opacity_g (n) (zeros for culled Gaussians), and sets
// g_viewmat (4,4) and g_K (3,3): the launcher zero-fills both on `stream`, then every block adds
// its warp-reduced partial sums with atomicAdd (so their float summation order is not fixed).
template <typename T>
cudaError_t launch_projection_bwd(const T* means, const T* quats, const T* scales,
                                  const T* opacity_c, const T* opacity_g, const T* viewmat,
                                  const T* K, int64_t n, int width, int height, T beta, T eps2d,
                                  bool antialiased, T near_plane, T far_plane,
                                  const T* v_means2d, const T* v_conics, const T* v_depths,
                                  const T* v_opacities, T* g_means, T* g_quats, T* g_scales,
                                  T* g_opacity_c, T* g_opacity_g, T* g_viewmat, T* g_K,
                                  cudaStream_t stream);

}  // namespace cuda
}  // namespace dgs
