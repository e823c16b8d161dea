// Device-side helpers shared by the CUDA kernels: warp reductions and float atomics. Only for
// .cu files (nvcc); the launcher headers (<op>_cuda.h) stay includable by the host compiler.
#pragma once

#if !defined(__CUDACC__)
#error "reduce_cuda.h is for .cu files compiled by nvcc"
#endif

#include <cuda_runtime.h>

#include <cstdint>

namespace dgs {
namespace cuda {

constexpr unsigned kFullMask = 0xffffffffu;
constexpr int kWarpSize = 32;

// Sum over the 32 lanes of a warp; the result is valid in lane 0. Every lane must call it
// (callers keep blocks a multiple of 32 threads and never return early).
template <typename T> __device__ __forceinline__ T warp_sum(T v) {
#pragma unroll
  for (int off = kWarpSize / 2; off > 0; off >>= 1) v += __shfl_down_sync(kFullMask, v, off);
  return v;
}

template <typename T> __device__ __forceinline__ T warp_max(T v) {
#pragma unroll
  for (int off = kWarpSize / 2; off > 0; off >>= 1) {
    const T o = __shfl_down_sync(kFullMask, v, off);
    v = o > v ? o : v;
  }
  return v;
}

// atomicMax for non-negative floating values: their bit patterns order like signed integers.
__device__ __forceinline__ void atomic_max_nonneg(float* addr, float v) {
  atomicMax(reinterpret_cast<int*>(addr), __float_as_int(v));
}
__device__ __forceinline__ void atomic_max_nonneg(double* addr, double v) {
  atomicMax(reinterpret_cast<unsigned long long*>(addr),
            static_cast<unsigned long long>(__double_as_longlong(v)));
}

// Blocks of `threads` threads rounded up to whole warps, so that full-mask shuffles are legal.
__host__ __device__ __forceinline__ int round_up_warp(int threads) {
  return (threads + kWarpSize - 1) / kWarpSize * kWarpSize;
}

}  // namespace cuda
}  // namespace dgs
