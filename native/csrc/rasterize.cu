// Blending of both branches on the GPU: one block per tile, one thread per pixel. The block walks
// the tile's depth-sorted list in batches staged in shared memory; each pixel applies the same
// per-branch rule as rasterize.cpp (skip alpha < 1/255; stop a branch, without adding the
// Gaussian, when T (1 - alpha) < 1e-4; the pixel is finished when both branches stopped).
//
// The backward pass walks front to back like the CPU kernel, recomputing T by multiplication and
// using the saved final outputs for the "what lies behind" term, so both give the same gradients.
// Per-Gaussian gradients are summed over the 32 pixels of a warp with shuffles, then lane 0 adds
// them with atomicAdd.
//
// Features: with a compile-time channel count the per-pixel sums (forward) and upstream
// gradients (backward) live in registers; with CC or GG = kDynamic the kernel loops over any
// number of channels in global memory. The per-Gaussian and per-pixel math is gaussian_math.h.
#include <cuda_runtime.h>

#include <type_traits>

#include "gaussian_math.h"
#include "rasterize_cuda.h"
#include "reduce_cuda.h"

namespace dgs {
namespace cuda {
namespace {

constexpr int kMaxTile = 16;
constexpr int kMaxThreads = kMaxTile * kMaxTile;  // one thread per pixel of a tile
constexpr int kDynamic = -1;

// One Gaussian of the tile list, staged in shared memory for the whole block.
template <typename T> struct Staged {
  T mx, my;
  Sym2<T> conic;
  T oc, og, z;
  int32_t gid;
  int32_t rect[4];
};

template <typename T>
__device__ __forceinline__ void stage(Staged<T>& s, int32_t gid, const T* means2d,
                                      const T* conics, const T* opac, const T* depths,
                                      const int32_t* rects) {
  s.gid = gid;
  s.mx = means2d[2 * gid];
  s.my = means2d[2 * gid + 1];
  s.conic = {conics[3 * gid], conics[3 * gid + 1], conics[3 * gid + 2]};
  s.oc = opac[2 * gid];
  s.og = opac[2 * gid + 1];
  s.z = depths[gid];
  for (int j = 0; j < 4; ++j) s.rect[j] = rects[4 * gid + j];
}

// Stages entries [b0, min(end, b0 + blockDim.x)) of a tile's list into shared memory, one per
// thread, and returns how many there are; the callers place the barriers around it.
template <typename T, typename Params>
__device__ __forceinline__ int stage_batch(Staged<T>* batch, const Params& p, int64_t b0,
                                           int64_t end) {
  if (b0 + threadIdx.x < end)
    stage(batch[threadIdx.x], p.flat_ids[b0 + threadIdx.x], p.means2d, p.conics, p.opacities,
          p.depths, p.rects);
  return int(end - b0 < int64_t(blockDim.x) ? end - b0 : int64_t(blockDim.x));
}

// The Gaussian falloff exp(x), x <= 0, of every (pixel, Gaussian) pair, in both passes: the
// hardware exp2 for float (__expf: within a few ulp over the range where alpha can reach 1/255,
// |x| < 6, i.e. ~1e-6 relative, against the 1e-4 the outputs are held to; about half the
// instructions of expf), the accurate one for double. Forward and backward call the same one, so
// they make the same threshold decisions.
__device__ __forceinline__ float falloff(float x) { return __expf(x); }
__device__ __forceinline__ double falloff(double x) { return exp(x); }

// Whether pixel (u, v) lies in the Gaussian's box. The CPU kernel also skips the pixels of the box
// outside the row span of the ellipse where alpha reaches 1/255; there alpha < 1/255 anyway, so
// evaluating them gives the same result (up to rounding at the threshold itself) and is cheaper
// on the GPU than the span's square root for every pixel.
template <typename T>
__device__ __forceinline__ bool in_box(const Staged<T>& s, int32_t u, int32_t v) {
  return u >= s.rect[0] && u <= s.rect[2] && v >= s.rect[1] && v <= s.rect[3];
}

// The pixel a thread owns; ghost threads (past the tile or the image) still take part in the
// block's loops and warp collectives with nothing to do.
struct PixelSlot {
  int64_t u, v, pix;
  bool inside;
};

__device__ __forceinline__ PixelSlot pixel_slot(int tile_size, int64_t tiles_x, int width,
                                                int height) {
  const int64_t tile = blockIdx.x;
  const int t = threadIdx.x;
  PixelSlot s;
  s.u = (tile % tiles_x) * tile_size + t % tile_size;
  s.v = (tile / tiles_x) * tile_size + t / tile_size;
  s.inside = t < tile_size * tile_size && s.u < width && s.v < height;
  s.pix = s.inside ? s.v * width + s.u : 0;
  return s;
}

// Register array length for N channels (at least 1, so that N = 0 and dynamic N compile).
template <int N> constexpr int kRegs = N > 0 ? N : 1;

// ---------------------------------------------------------------------------------------------
// Forward.

// out += w * feat over the channels: registers when N is fixed, the pixel's global row otherwise.
template <typename T, int N>
__device__ __forceinline__ void blend(T* acc, T* out_pix, const T* feat, int n, T w) {
  if constexpr (N >= 0) {
#pragma unroll
    for (int c = 0; c < N; ++c) acc[c] += w * feat[c];
  } else {
    for (int c = 0; c < n; ++c) out_pix[c] += w * feat[c];
  }
}

template <typename T, int N>
__device__ __forceinline__ void init_out(T* acc, T* out_pix, int n, bool inside) {
  if constexpr (N >= 0) {
#pragma unroll
    for (int c = 0; c < kRegs<N>; ++c) acc[c] = T(0);
  } else {
    if (inside)
      for (int c = 0; c < n; ++c) out_pix[c] = T(0);
  }
}

template <typename T, int N>
__device__ __forceinline__ void store_out(const T* acc, T* out_pix) {
  if constexpr (N > 0) {
#pragma unroll
    for (int c = 0; c < N; ++c) out_pix[c] = acc[c];
  }
}

// One branch at one pixel. Returns the weight alpha * T added (0 when skipped or stopped).
template <typename T>
__device__ __forceinline__ T forward_branch(T o, T vis, T& trans, bool& stopped) {
  bool clamped;
  const T al = branch_alpha(o, vis, clamped);
  if (!(al >= alpha_min<T>())) return T(0);
  const T nt = trans * (T(1) - al);
  if (nt < transmittance_min<T>()) {
    stopped = true;
    return T(0);
  }
  const T w = al * trans;
  trans = nt;
  return w;
}

template <typename T, int CC, int GG>
__global__ void __launch_bounds__(kMaxThreads)
    rasterize_fwd_kernel(RasterizeFwdParams<T> p, int64_t tiles_x) {
  __shared__ Staged<T> batch[kMaxThreads];
  // Per batch entry, the block's max of alpha * T: warps raise it in shared memory, and one
  // global atomic per entry and batch follows (instead of one per warp).
  __shared__ T batch_best[kMaxThreads];
  const PixelSlot px = pixel_slot(p.tile_size, tiles_x, p.width, p.height);
  const int64_t start = p.tile_offsets[blockIdx.x], end = p.tile_offsets[blockIdx.x + 1];
  const int32_t n_list = int32_t(end - start);
  const int C = CC >= 0 ? CC : p.C, G = GG >= 0 ? GG : p.G;
  T* out_c = p.out_color + px.pix * C;
  T* out_g = p.out_geometry + px.pix * G;

  T tc = T(1), tg = T(1), depth = T(0);
  int32_t stop_c = n_list, stop_g = p.geometry_branch ? n_list : 0;
  bool done_c = !px.inside, done_g = !px.inside || !p.geometry_branch;
  T acc_c[kRegs<CC>], acc_g[kRegs<GG>];
  init_out<T, CC>(acc_c, out_c, C, px.inside);
  init_out<T, GG>(acc_g, out_g, G, px.inside);
  const T pu = T(px.u) + T(0.5), pv = T(px.v) + T(0.5);
  const int lane = threadIdx.x % kWarpSize;

  for (int64_t b0 = start; b0 < end; b0 += blockDim.x) {
    // Also the barrier that lets the batch be overwritten.
    if (__syncthreads_count(done_c && done_g) == int(blockDim.x)) break;
    const int nb = stage_batch(batch, p, b0, end);
    batch_best[threadIdx.x] = T(0);
    __syncthreads();
    for (int j = 0; j < nb; ++j) {
      const Staged<T>& s = batch[j];
      const T dy = pv - s.my;
      T best = T(0);
      if (!(done_c && done_g) && in_box(s, int32_t(px.u), int32_t(px.v))) {
        const T dx = pu - s.mx;
        const T vis = falloff(gaussian_exponent(s.conic, dx, dy));
        const int32_t k = int32_t(b0 - start) + j;
        if (!done_c) {
          const T w = forward_branch(s.oc, vis, tc, done_c);
          if (done_c) stop_c = k;
          if (w > T(0)) {
            blend<T, CC>(acc_c, out_c, p.colors + int64_t(C) * s.gid, C, w);
            best = w;
          }
        }
        if (!done_g) {
          const T w = forward_branch(s.og, vis, tg, done_g);
          if (done_g) stop_g = k;
          if (w > T(0)) {
            blend<T, GG>(acc_g, out_g, p.geometry + int64_t(G) * s.gid, G, w);
            depth += w * s.z;
            best = best > w ? best : w;
          }
        }
      }
      if (__any_sync(kFullMask, best > T(0))) {
        best = warp_max_nonneg(best);
        if (lane == 0 && best > T(0)) atomic_max_nonneg(batch_best + j, best);
      }
    }
    __syncthreads();
    if (int(threadIdx.x) < nb && batch_best[threadIdx.x] > T(0))
      atomic_max_nonneg(p.contribution + batch[threadIdx.x].gid, batch_best[threadIdx.x]);
  }
  if (!px.inside) return;
  store_out<T, CC>(acc_c, out_c);
  store_out<T, GG>(acc_g, out_g);
  p.out_depth[px.pix] = depth;
  p.transmittance[2 * px.pix] = tc;
  p.transmittance[2 * px.pix + 1] = tg;
  p.stops[2 * px.pix] = stop_c;
  p.stops[2 * px.pix + 1] = stop_g;
}

// ---------------------------------------------------------------------------------------------
// Backward.

// Running state of one branch at one pixel (the CPU kernel's BranchState for one pixel).
template <typename T> struct BranchBwd {
  T trans, prefix, total, final_trans, v_alpha;
  int32_t stop;
};

// Upstream feature gradient of one pixel: registers when N is fixed, global memory otherwise.
template <typename T, int N> struct PixelGrad {
  T v[kRegs<N>];
  const T* row;  // the pixel's gradient row (dynamic N)
  __device__ __forceinline__ void load(const T* src, int n, bool inside) {
    row = src;
    if constexpr (N >= 0) {
#pragma unroll
      for (int c = 0; c < kRegs<N>; ++c) v[c] = (inside && c < N) ? src[c] : T(0);
    }
  }
  __device__ __forceinline__ T at(int c) const {
    if constexpr (N >= 0) return v[c];
    else return row[c];
  }
};

// Sum of feat[c] * g[c] after `init`, in the CPU kernel's order.
template <typename T, int N>
__device__ __forceinline__ T feature_dot(T init, const T* feat, const PixelGrad<T, N>& g, int n) {
  T acc = init;
  if constexpr (N >= 0) {
#pragma unroll
    for (int c = 0; c < N; ++c) acc += feat[c] * g.v[c];
  } else {
    for (int c = 0; c < n; ++c) acc += feat[c] * g.row[c];
  }
  return acc;
}

// One branch at one pixel (the CPU kernel's backward_branch). Returns dL/d(exponent); sets w, the
// weight alpha * T of the features (0 when skipped), and adds dL/do to g_o.
template <typename T, int N>
__device__ __forceinline__ T backward_branch(BranchBwd<T>& s, T o, T vis, const T* feat,
                                             const PixelGrad<T, N>& vf, int nf, T extra,
                                             T v_extra, T& w, T& g_o) {
  bool clamped;
  const T al = branch_alpha(o, vis, clamped);
  if (al < alpha_min<T>()) return T(0);
  const T tb = s.trans;
  w = al * tb;
  const T fdot = feature_dot<T, N>(extra * v_extra, feat, vf, nf);
  s.prefix += w * fdot;
  const T inv = T(1) / (T(1) - al);
  const T v_al = tb * fdot - (s.total - s.prefix) * inv + s.v_alpha * s.final_trans * inv;
  s.trans = tb * (T(1) - al);
  if (clamped) return T(0);
  g_o += v_al * vis;
  return v_al * al;
}

template <typename T> __device__ __forceinline__ void add_reduced(T* dst, T v, int lane) {
  v = warp_sum(v);
  if (lane == 0 && v != T(0)) atomicAdd(dst, v);
}

// dst[c] += sum over the warp of w * g[c], channel by channel (any channel count).
template <typename T, int N>
__device__ __forceinline__ void add_feature_grads(T* dst, T w, const PixelGrad<T, N>& g, int n,
                                                  int lane) {
  if (!__any_sync(kFullMask, w != T(0))) return;
  if constexpr (N >= 0) {
#pragma unroll
    for (int c = 0; c < N; ++c) add_reduced(dst + c, w * g.v[c], lane);
  } else {
    for (int c = 0; c < n; ++c) add_reduced(dst + c, w != T(0) ? w * g.row[c] : T(0), lane);
  }
}

// The per-Gaussian gradient scalars of one pixel, in the order the packed reduction keeps them:
// means2d (2), conic (3), opacities (2), depth (1), AbsGS sums (4), colors (C), geometry (G).
constexpr int kCommonGrads = 12;

template <typename T>
__device__ __forceinline__ T* grad_slot(const RasterizeBwdParams<T>& p, int64_t g, int idx, int C,
                                        int G) {
  if (idx < 2) return p.g_means2d + 2 * g + idx;
  if (idx < 5) return p.g_conics + 3 * g + (idx - 2);
  if (idx < 7) return p.g_opacities + 2 * g + (idx - 5);
  if (idx == 7) return p.g_depths + g;
  if (idx < kCommonGrads) return p.absgrad + 4 * g + (idx - 8);
  if (idx < kCommonGrads + C) return p.g_colors + int64_t(C) * g + (idx - kCommonGrads);
  return p.g_geometry + int64_t(G) * g + (idx - kCommonGrads - C);
}

// Fixed channel counts whose scalars fit one packed warp reduction (warp_sum_many).
template <int CC, int GG>
constexpr bool kPackedGrads = CC >= 0 && GG >= 0 && kCommonGrads + CC + GG <= kWarpSize;
template <int CC, int GG>
constexpr int kPackedWidth = kCommonGrads + CC + GG <= 16 ? 16 : kWarpSize;

template <typename T, int CC, int GG>
__global__ void __launch_bounds__(kMaxThreads)
    rasterize_bwd_kernel(RasterizeBwdParams<T> p, int64_t tiles_x) {
  __shared__ Staged<T> batch[kMaxThreads];
  __shared__ int32_t max_stop;
  const PixelSlot px = pixel_slot(p.tile_size, tiles_x, p.width, p.height);
  const int64_t start = p.tile_offsets[blockIdx.x];
  const int C = CC >= 0 ? CC : p.C, G = GG >= 0 ? GG : p.G;
  const int64_t pix = px.pix;

  PixelGrad<T, CC> vc;
  PixelGrad<T, GG> vg;
  vc.load(p.v_color + pix * C, C, px.inside);
  vg.load(p.v_geometry + pix * G, G, px.inside);
  BranchBwd<T> sc = {T(1), T(0), T(0), T(1), T(0), 0};
  BranchBwd<T> sg = sc;
  T v_depth = T(0);
  if (px.inside) {
    v_depth = p.v_depth[pix];
    T dc = T(0), dg = p.out_depth[pix] * v_depth;
    for (int c = 0; c < C; ++c) dc += p.out_color[pix * C + c] * vc.at(c);
    for (int c = 0; c < G; ++c) dg += p.out_geometry[pix * G + c] * vg.at(c);
    sc.total = dc;
    sg.total = dg;
    sc.final_trans = p.transmittance[2 * pix];
    sg.final_trans = p.transmittance[2 * pix + 1];
    // alpha = 1 - T_final, so dL/dT_final = -dL/dalpha; the sign is folded in backward_branch.
    sc.v_alpha = p.v_alpha[2 * pix];
    sg.v_alpha = p.v_alpha[2 * pix + 1];
    sc.stop = p.stops[2 * pix];
    sg.stop = p.stops[2 * pix + 1];
  }
  if (threadIdx.x == 0) max_stop = 0;
  __syncthreads();
  if (px.inside) atomicMax(&max_stop, sc.stop > sg.stop ? sc.stop : sg.stop);
  __syncthreads();
  const int64_t end = start + max_stop;
  const T pu = T(px.u) + T(0.5), pv = T(px.v) + T(0.5);
  const int lane = threadIdx.x % kWarpSize;

  for (int64_t b0 = start; b0 < end; b0 += blockDim.x) {
    __syncthreads();  // the previous batch is no longer read
    const int nb = stage_batch(batch, p, b0, end);
    __syncthreads();
    for (int j = 0; j < nb; ++j) {
      const Staged<T>& s = batch[j];
      const int32_t k = int32_t(b0 - start) + j;
      const bool in_c = px.inside && k < sc.stop, in_g = px.inside && k < sg.stop;
      const T dy = pv - s.my;
      T ve_c = T(0), ve_g = T(0), w_c = T(0), w_g = T(0), g_oc = T(0), g_og = T(0);
      Vec2<T> dm = {T(0), T(0)};
      Sym2<T> dcn = {T(0), T(0), T(0)};
      if ((in_c || in_g) && in_box(s, int32_t(px.u), int32_t(px.v))) {
        const T dx = pu - s.mx;
        const T vis = falloff(gaussian_exponent(s.conic, dx, dy));
        if (in_c)
          ve_c = backward_branch<T, CC>(sc, s.oc, vis, p.colors + int64_t(C) * s.gid, vc, C,
                                        T(0), T(0), w_c, g_oc);
        if (in_g)
          ve_g = backward_branch<T, GG>(sg, s.og, vis, p.geometry + int64_t(G) * s.gid, vg, G,
                                        s.z, v_depth, w_g, g_og);
        dm = exponent_dmean(s.conic, dx, dy);
        dcn = exponent_dconic(dx, dy);
      }
      const bool any_w = w_c != T(0) || w_g != T(0);
      if (!__any_sync(kFullMask, any_w || ve_c != T(0) || ve_g != T(0))) continue;
      const T ve = ve_c + ve_g;
      const int32_t g = s.gid;
      if constexpr (kPackedGrads<CC, GG>) {
        // One packed reduction: 16 or 31 shuffles for all scalars instead of 5 per scalar, and
        // the atomics spread over the lanes instead of serialized in lane 0.
        constexpr int K = kPackedWidth<CC, GG>;
        T v[K];
        v[0] = dm.x * ve; v[1] = dm.y * ve;
        v[2] = dcn.a * ve; v[3] = dcn.b * ve; v[4] = dcn.c * ve;
        v[5] = g_oc; v[6] = g_og; v[7] = w_g * v_depth;
        v[8] = fabs(dm.x * ve_c); v[9] = fabs(dm.y * ve_c);
        v[10] = fabs(dm.x * ve_g); v[11] = fabs(dm.y * ve_g);
#pragma unroll
        for (int c = 0; c < CC; ++c) v[kCommonGrads + c] = w_c * vc.v[c];
#pragma unroll
        for (int c = 0; c < GG; ++c) v[kCommonGrads + CC + c] = w_g * vg.v[c];
#pragma unroll
        for (int i = kCommonGrads + CC + GG; i < K; ++i) v[i] = T(0);
        warp_sum_many<T, K>(v, lane);
        const int idx = warp_sum_many_index<K>(lane);
        if (lane % (kWarpSize / K) == 0 && idx < kCommonGrads + CC + GG && v[0] != T(0))
          atomicAdd(grad_slot(p, g, idx, CC, GG), v[0]);
        continue;
      }
      add_reduced(p.g_means2d + 2 * g, dm.x * ve, lane);
      add_reduced(p.g_means2d + 2 * g + 1, dm.y * ve, lane);
      add_reduced(p.g_conics + 3 * g, dcn.a * ve, lane);
      add_reduced(p.g_conics + 3 * g + 1, dcn.b * ve, lane);
      add_reduced(p.g_conics + 3 * g + 2, dcn.c * ve, lane);
      add_reduced(p.g_opacities + 2 * g, g_oc, lane);
      add_reduced(p.g_opacities + 2 * g + 1, g_og, lane);
      add_reduced(p.g_depths + g, w_g * v_depth, lane);
      add_reduced(p.absgrad + 4 * g, fabs(dm.x * ve_c), lane);
      add_reduced(p.absgrad + 4 * g + 1, fabs(dm.y * ve_c), lane);
      add_reduced(p.absgrad + 4 * g + 2, fabs(dm.x * ve_g), lane);
      add_reduced(p.absgrad + 4 * g + 3, fabs(dm.y * ve_g), lane);
      add_feature_grads<T, CC>(p.g_colors + int64_t(C) * g, w_c, vc, C, lane);
      add_feature_grads<T, GG>(p.g_geometry + int64_t(G) * g, w_g, vg, G, lane);
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Launch: checks, zero-filling, and the choice of channel specialization.

template <int V> using Int = std::integral_constant<int, V>;

// Calls f(Int<CC>, Int<GG>) with the specialization for (C, G): fixed counts for the common
// float cases, the generic loop otherwise.
template <typename T, typename F> cudaError_t dispatch_channels(int C, int G, F&& f) {
  if constexpr (std::is_same<T, float>::value) {
    if (C == 3) {
      switch (G) {
        case 0: return f(Int<3>{}, Int<0>{});
        case 1: return f(Int<3>{}, Int<1>{});
        case 3: return f(Int<3>{}, Int<3>{});
        case 4: return f(Int<3>{}, Int<4>{});
        case 5: return f(Int<3>{}, Int<5>{});
        default: break;
      }
    }
  }
  return f(Int<kDynamic>{}, Int<kDynamic>{});
}

struct Launch {
  int64_t tiles_x, n_tiles;
  int threads;
};

// The sizes both passes share (taken as plain values: p.n < 0 in a template reads as a
// template-id to g++).
cudaError_t check_sizes(int64_t n, int C, int G, int width, int height, int tile_size,
                        bool geometry_branch, Launch& l) {
  if (n < 0 || n > INT32_MAX || C < 0 || G < 0 || width < 0 || height < 0 || tile_size < 1 ||
      tile_size > kMaxTile || (!geometry_branch && G != 0))
    return cudaErrorInvalidValue;
  l.tiles_x = (int64_t(width) + tile_size - 1) / tile_size;
  l.n_tiles = l.tiles_x * ((int64_t(height) + tile_size - 1) / tile_size);
  if (l.n_tiles > INT32_MAX) return cudaErrorInvalidValue;
  l.threads = round_up_warp(tile_size * tile_size);
  return cudaSuccess;
}

template <typename Params> cudaError_t check_params(const Params& p, Launch& l) {
  return check_sizes(p.n, p.C, p.G, p.width, p.height, p.tile_size, p.geometry_branch, l);
}

template <typename T> cudaError_t zero(T* ptr, int64_t count, cudaStream_t stream) {
  if (count == 0) return cudaSuccess;
  return cudaMemsetAsync(ptr, 0, size_t(count) * sizeof(T), stream);
}

}  // namespace

template <typename T>
cudaError_t launch_rasterize_fwd(const RasterizeFwdParams<T>& p, cudaStream_t stream) {
  Launch l;
  cudaError_t err = check_params(p, l);
  if (err != cudaSuccess) return err;
  if ((err = zero(p.contribution, p.n, stream)) != cudaSuccess) return err;
  if (l.n_tiles == 0) return cudaSuccess;
  return dispatch_channels<T>(p.C, p.G, [&](auto cc, auto gg) {
    rasterize_fwd_kernel<T, decltype(cc)::value, decltype(gg)::value>
        <<<unsigned(l.n_tiles), l.threads, 0, stream>>>(p, l.tiles_x);
    return cudaGetLastError();
  });
}

template <typename T>
cudaError_t launch_rasterize_bwd(const RasterizeBwdParams<T>& p, cudaStream_t stream) {
  Launch l;
  cudaError_t err = check_params(p, l);
  if (err != cudaSuccess) return err;
  const int64_t n = p.n;
  if ((err = zero(p.g_means2d, 2 * n, stream)) != cudaSuccess) return err;
  if ((err = zero(p.g_conics, 3 * n, stream)) != cudaSuccess) return err;
  if ((err = zero(p.g_opacities, 2 * n, stream)) != cudaSuccess) return err;
  if ((err = zero(p.g_depths, n, stream)) != cudaSuccess) return err;
  if ((err = zero(p.g_colors, int64_t(p.C) * n, stream)) != cudaSuccess) return err;
  if ((err = zero(p.g_geometry, int64_t(p.G) * n, stream)) != cudaSuccess) return err;
  if ((err = zero(p.absgrad, 4 * n, stream)) != cudaSuccess) return err;
  if (l.n_tiles == 0 || n == 0) return cudaSuccess;
  return dispatch_channels<T>(p.C, p.G, [&](auto cc, auto gg) {
    rasterize_bwd_kernel<T, decltype(cc)::value, decltype(gg)::value>
        <<<unsigned(l.n_tiles), l.threads, 0, stream>>>(p, l.tiles_x);
    return cudaGetLastError();
  });
}

template cudaError_t launch_rasterize_fwd<float>(const RasterizeFwdParams<float>&, cudaStream_t);
template cudaError_t launch_rasterize_fwd<double>(const RasterizeFwdParams<double>&,
                                                  cudaStream_t);
template cudaError_t launch_rasterize_bwd<float>(const RasterizeBwdParams<float>&, cudaStream_t);
template cudaError_t launch_rasterize_bwd<double>(const RasterizeBwdParams<double>&,
                                                  cudaStream_t);

}  // namespace cuda
}  // namespace dgs
