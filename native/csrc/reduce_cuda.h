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

// Max over the warp of non-negative values, valid in every lane: one redux instruction for float
// (sm_80+; the bit patterns of non-negative floats order like unsigned integers), shuffles else.
__device__ __forceinline__ float warp_max_nonneg(float v) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  return __uint_as_float(__reduce_max_sync(kFullMask, __float_as_uint(v)));
#else
  return warp_max(v);
#endif
}
__device__ __forceinline__ double warp_max_nonneg(double v) { return warp_max(v); }

// Sums K values (K a power of two, at most 32) over the 32 lanes of a warp with K - 1 + log2(32/K)
// shuffles instead of 5K (one warp_sum each): at each step a lane keeps half of its values and
// trades the other half with the lane `off` apart, which keeps the opposite half. Afterwards v[0]
// of lane l holds the warp's sum of value number warp_sum_many_index<K>(l), in every lane of the
// group of 32 / K lanes that share it. Every lane must call it.
template <int K> __device__ __forceinline__ int warp_sum_many_index(int lane) {
  return lane / (kWarpSize / K);
}

// One step of warp_sum_many: values [0, 2 * Half) become [0, Half), traded with lane `Off` apart.
// A template per step, so that every index is a compile-time constant and v stays in registers
// (a loop over steps with an inner loop bound that depends on the step is not unrolled by nvcc,
// which then puts v in local memory).
template <typename T, int K, int Half, int Off>
__device__ __forceinline__ void warp_sum_many_step(T (&v)[K], int lane) {
  if constexpr (Half >= 1) {
    const bool upper = (lane & Off) != 0;
#pragma unroll
    for (int i = 0; i < Half; ++i) {
      const T send = upper ? v[i] : v[i + Half];
      const T keep = upper ? v[i + Half] : v[i];
      v[i] = keep + __shfl_xor_sync(kFullMask, send, Off);
    }
    warp_sum_many_step<T, K, Half / 2, Off / 2>(v, lane);
  } else {
#pragma unroll
    for (int off = Off; off > 0; off >>= 1) v[0] += __shfl_xor_sync(kFullMask, v[0], off);
  }
}

template <typename T, int K> __device__ __forceinline__ void warp_sum_many(T (&v)[K], int lane) {
  static_assert(K >= 1 && K <= kWarpSize && (K & (K - 1)) == 0, "K: a power of two <= 32");
  warp_sum_many_step<T, K, K / 2, kWarpSize / 2>(v, lane);
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
