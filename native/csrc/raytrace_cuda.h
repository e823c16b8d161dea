// CUDA launcher of the ray tracer (raytrace.cu). No torch here; see projection_cuda.h for the
// conventions (device pointers, asynchronous on `stream`, cudaError_t launch status).
//
// The BVH is built on the host (build_bvh in raytrace_bvh.h) and its flat arrays copied to the
// device; `bvh` is a BvhView whose pointers are all device pointers (nodes, order, mean (n,3),
// inv_cov (n,9), lo (n,3), hi (n,3), opacity (n)), n = bvh.n Gaussians (0: no tree, every
// pointer may be null and every visibility is 1). The walk is raytrace_bvh.h's, the one the CPU
// op runs, so results equal raytrace.cpp up to float rounding (nvcc contracts a*b+c into FMA,
// and the device's cos/sin/exp round differently from the host's).
#pragma once

#include <cuda_runtime_api.h>

#include <cstdint>

#include "raytrace_bvh.h"

namespace dgs {
namespace cuda {

// origins (m,3), normals (m,3) unit, exclude (m) int64 (a Gaussian id each origin ignores, or
// -1). Writes every entry of visibility (m). m == 0 launches nothing and succeeds; a negative
// m, a negative bvh.n or n_dirs < 1 returns cudaErrorInvalidValue.
template <typename T>
cudaError_t launch_trace_visibility(const T* origins, const T* normals, const int64_t* exclude,
                                    int64_t m, BvhView<T> bvh, int n_dirs, T* visibility,
                                    cudaStream_t stream);

}  // namespace cuda
}  // namespace dgs
