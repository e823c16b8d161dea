// Ray tracer on the GPU: one thread per origin, running raytrace_bvh.h's origin_visibility (the
// CPU op's per-origin loop) over the host-built tree in device memory.
//
// Why a thread per origin rather than per (origin, direction) with a reduction: each thread sums
// its rays in the CPU's order (num and den over k = 0..n_dirs-1), so the two ops differ only by
// per-ray rounding, and no reduction, shared memory or atomics are needed. It fills the GPU once
// m reaches a few hundred thousand origins (gaussian_visibility traces one per Gaussian); with
// few origins and many directions a thread per ray would keep more of it busy (to measure).
// The traversal stack (kStackSize int32 entries) lives in local memory, as on the CPU.
#include <cuda_runtime.h>

#include "raytrace_bvh.h"
#include "raytrace_cuda.h"

namespace dgs {
namespace cuda {
namespace {

constexpr int kThreads = 128;

template <typename T>
__global__ void __launch_bounds__(kThreads)
    trace_visibility_kernel(const T* __restrict__ origins, const T* __restrict__ normals,
                            const int64_t* __restrict__ exclude, int64_t m, BvhView<T> bvh,
                            int n_dirs, T* __restrict__ visibility) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= m) return;  // no collectives in this kernel
  visibility[i] = origin_visibility(bvh, origins + 3 * i, normals + 3 * i, exclude[i], n_dirs);
}

}  // namespace

template <typename T>
cudaError_t launch_trace_visibility(const T* origins, const T* normals, const int64_t* exclude,
                                    int64_t m, BvhView<T> bvh, int n_dirs, T* visibility,
                                    cudaStream_t stream) {
  if (m < 0 || bvh.n < 0 || n_dirs < 1) return cudaErrorInvalidValue;
  if (m == 0) return cudaSuccess;
  const int64_t blocks = (m + kThreads - 1) / kThreads;
  if (blocks > int64_t(0x7fffffff)) return cudaErrorInvalidValue;  // grid x limit
  trace_visibility_kernel<T><<<unsigned(blocks), kThreads, 0, stream>>>(
      origins, normals, exclude, m, bvh, n_dirs, visibility);
  return cudaGetLastError();
}

#define DGS_INSTANTIATE_RAYTRACE(T)                                                        \
  template cudaError_t launch_trace_visibility<T>(const T*, const T*, const int64_t*, int64_t, \
                                                  BvhView<T>, int, T*, cudaStream_t);

DGS_INSTANTIATE_RAYTRACE(float)
DGS_INSTANTIATE_RAYTRACE(double)
#undef DGS_INSTANTIATE_RAYTRACE

}  // namespace cuda
}  // namespace dgs
