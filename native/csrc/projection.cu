// Projection: CUDA kernels, one thread per Gaussian. The per-Gaussian math, project_one
// included, is gaussian_math.h, shared with projection.cpp so both give the same values.
#include <cuda_runtime.h>

#include "gaussian_math.h"
#include "projection_cuda.h"
#include "reduce_cuda.h"

namespace dgs {
namespace cuda {
namespace {

constexpr int kThreads = 256;

template <typename T>
__global__ void __launch_bounds__(kThreads)
    projection_fwd_kernel(const T* __restrict__ means, const T* __restrict__ quats,
                          const T* __restrict__ scales, const T* __restrict__ opacity_c,
                          const T* __restrict__ opacity_g, const T* __restrict__ viewmat,
                          const T* __restrict__ K, int64_t n, int width, int height, T beta,
                          T eps2d, bool antialiased, T near_plane, T far_plane,
                          T* __restrict__ means2d, T* __restrict__ conics, T* __restrict__ depths,
                          T* __restrict__ opac, int32_t* __restrict__ rects,
                          int32_t* __restrict__ radii) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;  // no warp collectives in this kernel
  const ProjCamera<T> cam = camera_from(viewmat, K, width, height);
  T mx = T(0), my = T(0), o_c = T(0), o_g = T(0), z = T(0);
  Sym2<T> conic = {T(0), T(0), T(0)};
  int32_t rect[4] = {0, 0, -1, -1};
  int32_t radius = 0;
  const Projected<T> g = project_one(means + 3 * i, quats + 4 * i, scales + 3 * i, cam, eps2d,
                                     antialiased, near_plane, far_plane);
  if (g.valid) {
    mix_opacities(opacity_c[i], opacity_g[i], beta, g.comp, o_c, o_g);
    mx = cam.k.fx * g.p.x / g.p.z + cam.k.cx;
    my = cam.k.fy * g.p.y / g.p.z + cam.k.cy;
    conic = inverse2(g.cov2d);
    z = g.p.z;
    T ex, ey;
    int32_t r[4];
    if (screen_extent(g.cov2d, o_c > o_g ? o_c : o_g, ex, ey) &&
        pixel_rect(mx, my, ex, ey, width, height, r)) {
      for (int j = 0; j < 4; ++j) rect[j] = r[j];
      const T rr = m_ceil(ex > ey ? ex : ey);
      radius = rr < T(1) ? 1 : int32_t(rr);
    }
  }
  means2d[2 * i] = mx; means2d[2 * i + 1] = my;
  conics[3 * i] = conic.a; conics[3 * i + 1] = conic.b; conics[3 * i + 2] = conic.c;
  depths[i] = z;
  opac[2 * i] = o_c; opac[2 * i + 1] = o_g;
  for (int j = 0; j < 4; ++j) rects[4 * i + j] = rect[j];
  radii[i] = radius;
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    projection_bwd_kernel(const T* __restrict__ means, const T* __restrict__ quats,
                          const T* __restrict__ scales, const T* __restrict__ opacity_c,
                          const T* __restrict__ opacity_g, const T* __restrict__ viewmat,
                          const T* __restrict__ K, int64_t n, int width, int height, T beta,
                          T eps2d, bool antialiased, T near_plane, T far_plane,
                          const T* __restrict__ v_means2d, const T* __restrict__ v_conics,
                          const T* __restrict__ v_depths, const T* __restrict__ v_opac,
                          T* __restrict__ g_means, T* __restrict__ g_quats,
                          T* __restrict__ g_scales, T* __restrict__ g_op_c,
                          T* __restrict__ g_op_g, T* __restrict__ g_viewmat,
                          T* __restrict__ g_K) {
  // Camera gradient of this thread: rotation (9), translation (3), fx fy cx cy (4), as in the
  // CPU kernel. Threads past n keep zeros but stay for the block reduction.
  T local[16];
#pragma unroll
  for (int j = 0; j < 16; ++j) local[j] = T(0);
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < n) {
    const ProjCamera<T> cam = camera_from(viewmat, K, width, height);
    const Projected<T> g = project_one(means + 3 * i, quats + 4 * i, scales + 3 * i, cam, eps2d,
                                       antialiased, near_plane, far_plane);
    T gm[3] = {T(0), T(0), T(0)}, gq[4] = {T(0), T(0), T(0), T(0)}, gs[3] = {T(0), T(0), T(0)};
    T goc = T(0), gog = T(0);
    if (g.valid) {
      const ProjectionGrads<T> pg = project_one_vjp(
          g, means + 3 * i, quats + 4 * i, scales + 3 * i, opacity_c[i], opacity_g[i], cam, beta,
          eps2d, antialiased, v_means2d + 2 * i, v_conics + 3 * i, v_depths[i], v_opac + 2 * i);
#pragma unroll
      for (int j = 0; j < 3; ++j) gm[j] = pg.mean[j];
#pragma unroll
      for (int j = 0; j < 4; ++j) gq[j] = pg.quat[j];
#pragma unroll
      for (int j = 0; j < 3; ++j) gs[j] = pg.scale[j];
      goc = pg.op_c;
      gog = pg.op_g;
#pragma unroll
      for (int j = 0; j < 16; ++j) local[j] = pg.camera[j];
    }
    for (int j = 0; j < 3; ++j) g_means[3 * i + j] = gm[j];
    for (int j = 0; j < 4; ++j) g_quats[4 * i + j] = gq[j];
    for (int j = 0; j < 3; ++j) g_scales[3 * i + j] = gs[j];
    g_op_c[i] = goc;
    g_op_g[i] = gog;
  }
  // Block reduction of the camera gradient: shuffles inside each warp, shared memory across
  // warps, then one atomicAdd per entry per block.
  __shared__ T partial[kThreads / kWarpSize][16];
  const int lane = threadIdx.x % kWarpSize, warp = threadIdx.x / kWarpSize;
#pragma unroll
  for (int j = 0; j < 16; ++j) {
    const T s = warp_sum(local[j]);
    if (lane == 0) partial[warp][j] = s;
  }
  __syncthreads();
  if (threadIdx.x < 16) {
    const int j = threadIdx.x;
    T s = T(0);
    for (int w = 0; w < int(blockDim.x) / kWarpSize; ++w) s += partial[w][j];
    // Entry j -> viewmat (a, b) for j < 9, viewmat (a, 3) for j < 12, then fx, fy, cx, cy.
    T* dst = j < 9 ? g_viewmat + 4 * (j / 3) + j % 3
             : j < 12 ? g_viewmat + 4 * (j - 9) + 3
             : j == 12 ? g_K + 0
             : j == 13 ? g_K + 4
             : j == 14 ? g_K + 2
                       : g_K + 5;
    if (s != T(0)) atomicAdd(dst, s);
  }
}

inline unsigned blocks_for(int64_t n) { return unsigned((n + kThreads - 1) / kThreads); }

}  // namespace

template <typename T>
cudaError_t launch_projection_fwd(const T* means, const T* quats, const T* scales,
                                  const T* opacity_c, const T* opacity_g, const T* viewmat,
                                  const T* K, int64_t n, int width, int height, T beta, T eps2d,
                                  bool antialiased, T near_plane, T far_plane, T* means2d,
                                  T* conics, T* depths, T* opacities, int32_t* rects,
                                  int32_t* radii, cudaStream_t stream) {
  if (n < 0 || width < 0 || height < 0) return cudaErrorInvalidValue;
  if (n == 0) return cudaSuccess;
  projection_fwd_kernel<T><<<blocks_for(n), kThreads, 0, stream>>>(
      means, quats, scales, opacity_c, opacity_g, viewmat, K, n, width, height, beta, eps2d,
      antialiased, near_plane, far_plane, means2d, conics, depths, opacities, rects, radii);
  return cudaGetLastError();
}

template <typename T>
cudaError_t launch_projection_bwd(const T* means, const T* quats, const T* scales,
                                  const T* opacity_c, const T* opacity_g, const T* viewmat,
                                  const T* K, int64_t n, int width, int height, T beta, T eps2d,
                                  bool antialiased, T near_plane, T far_plane,
                                  const T* v_means2d, const T* v_conics, const T* v_depths,
                                  const T* v_opacities, T* g_means, T* g_quats, T* g_scales,
                                  T* g_opacity_c, T* g_opacity_g, T* g_viewmat, T* g_K,
                                  cudaStream_t stream) {
  if (n < 0 || width < 0 || height < 0) return cudaErrorInvalidValue;
  cudaError_t err = cudaMemsetAsync(g_viewmat, 0, 16 * sizeof(T), stream);
  if (err != cudaSuccess) return err;
  err = cudaMemsetAsync(g_K, 0, 9 * sizeof(T), stream);
  if (err != cudaSuccess) return err;
  if (n == 0) return cudaSuccess;
  projection_bwd_kernel<T><<<blocks_for(n), kThreads, 0, stream>>>(
      means, quats, scales, opacity_c, opacity_g, viewmat, K, n, width, height, beta, eps2d,
      antialiased, near_plane, far_plane, v_means2d, v_conics, v_depths, v_opacities, g_means,
      g_quats, g_scales, g_opacity_c, g_opacity_g, g_viewmat, g_K);
  return cudaGetLastError();
}

#define DGS_INSTANTIATE_PROJECTION(T)                                                          \
  template cudaError_t launch_projection_fwd<T>(                                               \
      const T*, const T*, const T*, const T*, const T*, const T*, const T*, int64_t, int, int, \
      T, T, bool, T, T, T*, T*, T*, T*, int32_t*, int32_t*, cudaStream_t);                     \
  template cudaError_t launch_projection_bwd<T>(                                               \
      const T*, const T*, const T*, const T*, const T*, const T*, const T*, int64_t, int, int, \
      T, T, bool, T, T, const T*, const T*, const T*, const T*, T*, T*, T*, T*, T*, T*, T*,    \
      cudaStream_t);

DGS_INSTANTIATE_PROJECTION(float)
DGS_INSTANTIATE_PROJECTION(double)
#undef DGS_INSTANTIATE_PROJECTION

}  // namespace cuda
}  // namespace dgs
