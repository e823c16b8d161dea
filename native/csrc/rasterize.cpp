// Rasterization of both branches on the CPU: parallel over 16x16 tiles; each Gaussian of a tile's
// depth-sorted list is evaluated only inside its pixel box. The backward pass walks the same list
// front to back, recomputing transmittance by multiplication (no division back through alphas),
// and accumulates per-Gaussian gradients in per-thread buffers that are summed at the end, so no
// atomics are needed. The thread count follows the image size (`raster_parts`).
#include "rasterize.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "checks.h"
#include "gaussian_math.h"

namespace dgs {
namespace {

struct Tiling {
  int64_t width, height, size, tiles_x, tiles_y;
  int64_t count() const { return tiles_x * tiles_y; }
};

// The pixel box of one tile.
struct TileBox {
  int64_t x0, y0, w, h;
};

// Tiles per thread below which a second thread costs more than it saves: each thread adds a
// per-Gaussian buffer to zero and sum (O(N), whatever the image size) and a share of every
// synchronisation, which a small image's tiles do not repay (135x240 is 135 tiles).
constexpr int64_t kTilesPerThread = 192;

// How many contiguous parts (one thread each, each with its own buffers) the tiles are split in.
inline int64_t raster_parts(const Tiling& t) {
  return std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(),
                                                t.count() / kTilesPerThread));
}

// Runs body(part, first tile, end tile) for each part in parallel; part indexes the buffers.
template <typename F> void for_parts(const Tiling& t, int64_t parts, const F& body) {
  const int64_t per = (t.count() + parts - 1) / parts;
  at::parallel_for(0, parts, 1, [&](int64_t begin, int64_t end) {
    for (int64_t p = begin; p < end; ++p)
      body(p, p * per, std::min(t.count(), (p + 1) * per));
  });
}

inline TileBox tile_box(const Tiling& t, int64_t tile) {
  const int64_t x0 = (tile % t.tiles_x) * t.size, y0 = (tile / t.tiles_x) * t.size;
  return {x0, y0, std::min(t.size, t.width - x0), std::min(t.size, t.height - y0)};
}

// The part of a Gaussian's rectangle inside a tile (never empty for a binned Gaussian).
inline void clip_rect(const int32_t* r, const TileBox& b, int64_t& u0, int64_t& u1, int64_t& v0,
                      int64_t& v1) {
  u0 = std::max<int64_t>(r[0], b.x0);
  u1 = std::min<int64_t>(r[2], b.x0 + b.w - 1);
  v0 = std::max<int64_t>(r[1], b.y0);
  v1 = std::min<int64_t>(r[3], b.y0 + b.h - 1);
}

template <typename T> struct FwdArgs {
  const T *means2d, *conics, *opac, *depths, *colors, *geometry;
  const int32_t *rects, *ids;
  const int64_t* offsets;
  int64_t n, C, G;
  T *out_color, *out_geo, *out_depth, *trans;
  int32_t* stops;
  T* contrib;  // (parts, N)
  bool geometry_branch;  // false: appearance only (a plain single-opacity RGB pass)
};

template <typename T> void forward_tile(const FwdArgs<T>& a, const Tiling& tl, int64_t tile,
                                        std::vector<T>& tcs, std::vector<T>& tgs,
                                        std::vector<int32_t>& stop_c, std::vector<int32_t>& stop_g,
                                        std::vector<uint8_t>& done, T* contrib) {
  const TileBox b = tile_box(tl, tile);
  const int64_t start = a.offsets[tile], end = a.offsets[tile + 1];
  const int32_t n_list = int32_t(end - start);
  const int64_t npix = b.w * b.h;
  std::fill(tcs.begin(), tcs.end(), T(1));
  std::fill(tgs.begin(), tgs.end(), T(1));
  std::fill(stop_c.begin(), stop_c.end(), n_list);
  // Without the geometry branch every pixel starts with that branch finished at position 0.
  std::fill(stop_g.begin(), stop_g.end(), a.geometry_branch ? n_list : 0);
  std::fill(done.begin(), done.end(), uint8_t(a.geometry_branch ? 0 : 2));
  int64_t n_done = 0;
  const int64_t C = a.C, G = a.G, W = tl.width, S = tl.size;
  for (int64_t k = start; k < end && n_done < npix; ++k) {
    const int32_t gid = a.ids[k];
    int64_t u0, u1, v0, v1;
    clip_rect(a.rects + 4 * gid, b, u0, u1, v0, v1);
    const T mx = a.means2d[2 * gid], my = a.means2d[2 * gid + 1];
    const Sym2<T> conic = {a.conics[3 * gid], a.conics[3 * gid + 1], a.conics[3 * gid + 2]};
    const T oc = a.opac[2 * gid], og = a.opac[2 * gid + 1], z = a.depths[gid];
    const T* col = a.colors + C * gid;
    const T* geo = a.geometry + G * gid;
    const T kq = level_k(a.geometry_branch && og > oc ? og : oc);
    T best = T(0);
    for (int64_t v = v0; v <= v1; ++v) {
      const T dy = T(v) + T(0.5) - my;
      int64_t s0, s1;
      if (!row_span(conic, kq, mx, dy, s0, s1)) continue;
      s0 = std::max(s0, u0);
      s1 = std::min(s1, u1);
      for (int64_t u = s0; u <= s1; ++u) {
        const int64_t l = (v - b.y0) * S + (u - b.x0);
        uint8_t d = done[l];
        if (d == 3) continue;
        const T dx = T(u) + T(0.5) - mx;
        const T vis = m_exp(gaussian_exponent(conic, dx, dy));
        const int64_t pix = v * W + u;
        bool clamped;
        if (!(d & 1)) {
          const T al = branch_alpha(oc, vis, clamped);
          if (al >= alpha_min<T>()) {
            const T nt = tcs[l] * (T(1) - al);
            if (nt < transmittance_min<T>()) {
              d |= 1;
              stop_c[l] = int32_t(k - start);
            } else {
              const T w = al * tcs[l];
              T* out = a.out_color + C * pix;
              for (int64_t c = 0; c < C; ++c) out[c] += w * col[c];
              tcs[l] = nt;
              best = std::max(best, w);
            }
          }
        }
        if (!(d & 2)) {
          const T al = branch_alpha(og, vis, clamped);
          if (al >= alpha_min<T>()) {
            const T nt = tgs[l] * (T(1) - al);
            if (nt < transmittance_min<T>()) {
              d |= 2;
              stop_g[l] = int32_t(k - start);
            } else {
              const T w = al * tgs[l];
              T* out = a.out_geo + G * pix;
              for (int64_t c = 0; c < G; ++c) out[c] += w * geo[c];
              a.out_depth[pix] += w * z;
              tgs[l] = nt;
              best = std::max(best, w);
            }
          }
        }
        if (d == 3) ++n_done;
        done[l] = d;
      }
    }
    contrib[gid] = std::max(contrib[gid], best);
  }
  for (int64_t v = 0; v < b.h; ++v)
    for (int64_t u = 0; u < b.w; ++u) {
      const int64_t l = v * S + u, pix = (b.y0 + v) * W + (b.x0 + u);
      a.trans[2 * pix] = tcs[l];
      a.trans[2 * pix + 1] = tgs[l];
      a.stops[2 * pix] = stop_c[l];
      a.stops[2 * pix + 1] = stop_g[l];
    }
}

template <typename T> struct BwdArgs {
  const T *means2d, *conics, *opac, *depths, *colors, *geometry;
  const int32_t *rects, *ids;
  const int64_t* offsets;
  int64_t n, C, G;
  const T *out_color, *out_geo, *out_depth, *trans;
  const int32_t* stops;
  const T *v_color, *v_geo, *v_depth, *v_alpha;
  // Per-thread gradient buffers: (threads, N, 8) [mean x, mean y, conic a b c, o_c, o_g, depth],
  // (threads, N, 4) AbsGS, (threads, N, C), (threads, N, G).
  T *g_param, *g_abs, *g_color, *g_geo;
  bool geometry_branch;
};

// Running per-pixel state of the backward walk for one branch.
template <typename T> struct BranchState {
  std::vector<T> trans, prefix, total, final_trans, v_alpha;
  std::vector<int32_t> stop;
  explicit BranchState(int64_t n)
      : trans(n), prefix(n), total(n), final_trans(n), v_alpha(n), stop(n) {}
};

// One branch at one pixel: returns dL/d(exponent) and adds to the feature gradients.
template <typename T>
inline T backward_branch(BranchState<T>& s, int64_t l, T o, T vis, const T* feat,
                         const T* v_feat, int64_t nf, T* g_feat, T extra_feat, T v_extra,
                         T& g_extra, T& g_o) {
  bool clamped;
  const T al = branch_alpha(o, vis, clamped);
  if (al < alpha_min<T>()) return T(0);
  const T tb = s.trans[l];
  const T w = al * tb;
  T fdot = extra_feat * v_extra;
  for (int64_t c = 0; c < nf; ++c) {
    fdot += feat[c] * v_feat[c];
    g_feat[c] += w * v_feat[c];
  }
  g_extra += w * v_extra;
  s.prefix[l] += w * fdot;
  const T inv = T(1) / (T(1) - al);
  const T v_al = tb * fdot - (s.total[l] - s.prefix[l]) * inv + s.v_alpha[l] * s.final_trans[l] * inv;
  s.trans[l] = tb * (T(1) - al);
  if (clamped) return T(0);
  g_o += v_al * vis;
  return v_al * al;
}

template <typename T> void backward_tile(const BwdArgs<T>& a, const Tiling& tl, int64_t tile,
                                         BranchState<T>& sc, BranchState<T>& sg,
                                         std::vector<T>& acc, int part) {
  const TileBox b = tile_box(tl, tile);
  const int64_t start = a.offsets[tile];
  const int64_t C = a.C, G = a.G, W = tl.width, S = tl.size, N = a.n;
  int32_t max_stop = 0;
  for (int64_t v = 0; v < b.h; ++v)
    for (int64_t u = 0; u < b.w; ++u) {
      const int64_t l = v * S + u, pix = (b.y0 + v) * W + (b.x0 + u);
      T dc = T(0), dg = a.out_depth[pix] * a.v_depth[pix];
      for (int64_t c = 0; c < C; ++c) dc += a.out_color[C * pix + c] * a.v_color[C * pix + c];
      for (int64_t c = 0; c < G; ++c) dg += a.out_geo[G * pix + c] * a.v_geo[G * pix + c];
      sc.trans[l] = T(1); sg.trans[l] = T(1);
      sc.prefix[l] = T(0); sg.prefix[l] = T(0);
      sc.total[l] = dc; sg.total[l] = dg;
      sc.final_trans[l] = a.trans[2 * pix]; sg.final_trans[l] = a.trans[2 * pix + 1];
      // alpha = 1 - T_final, so dL/dT_final = -dL/dalpha; the sign is folded in backward_branch.
      sc.v_alpha[l] = a.v_alpha[2 * pix]; sg.v_alpha[l] = a.v_alpha[2 * pix + 1];
      sc.stop[l] = a.stops[2 * pix]; sg.stop[l] = a.stops[2 * pix + 1];
      max_stop = std::max(max_stop, std::max(sc.stop[l], sg.stop[l]));
    }
  T* gp_base = a.g_param + int64_t(part) * N * 8;
  T* ga_base = a.g_abs + int64_t(part) * N * 4;
  T* gc_base = a.g_color + int64_t(part) * N * C;
  T* gg_base = a.g_geo + int64_t(part) * N * G;
  for (int32_t k = 0; k < max_stop; ++k) {
    const int32_t gid = a.ids[start + k];
    int64_t u0, u1, v0, v1;
    clip_rect(a.rects + 4 * gid, b, u0, u1, v0, v1);
    const T mx = a.means2d[2 * gid], my = a.means2d[2 * gid + 1];
    const Sym2<T> conic = {a.conics[3 * gid], a.conics[3 * gid + 1], a.conics[3 * gid + 2]};
    const T oc = a.opac[2 * gid], og = a.opac[2 * gid + 1], z = a.depths[gid];
    const T* col = a.colors + C * gid;
    const T* geo = a.geometry + G * gid;
    // Feature gradients of this Gaussian over this tile, flushed once at the end.
    T* gcol = acc.data();
    T* ggeo = acc.data() + C;
    std::fill(acc.begin(), acc.end(), T(0));
    const T kq = level_k(a.geometry_branch && og > oc ? og : oc);
    Vec2<T> g_mean = {T(0), T(0)};
    Sym2<T> g_conic = {T(0), T(0), T(0)};
    T g_oc = T(0), g_og = T(0), g_z = T(0), unused = T(0);
    T abs_c[2] = {T(0), T(0)}, abs_g[2] = {T(0), T(0)};
    for (int64_t v = v0; v <= v1; ++v) {
      const T dy = T(v) + T(0.5) - my;
      int64_t s0, s1;
      if (!row_span(conic, kq, mx, dy, s0, s1)) continue;
      s0 = std::max(s0, u0);
      s1 = std::min(s1, u1);
      for (int64_t u = s0; u <= s1; ++u) {
        const int64_t l = (v - b.y0) * S + (u - b.x0);
        const bool in_c = k < sc.stop[l], in_g = k < sg.stop[l];
        if (!in_c && !in_g) continue;
        const T dx = T(u) + T(0.5) - mx;
        const T vis = m_exp(gaussian_exponent(conic, dx, dy));
        const int64_t pix = v * W + u;
        const T ve_c = in_c ? backward_branch(sc, l, oc, vis, col, a.v_color + C * pix, C, gcol,
                                              T(0), T(0), unused, g_oc)
                            : T(0);
        const T ve_g = in_g ? backward_branch(sg, l, og, vis, geo, a.v_geo + G * pix, G, ggeo, z,
                                              a.v_depth[pix], g_z, g_og)
                            : T(0);
        const T ve = ve_c + ve_g;
        if (ve == T(0)) continue;
        const Vec2<T> dm = exponent_dmean(conic, dx, dy);
        const Sym2<T> dcn = exponent_dconic(dx, dy);
        g_mean.x += dm.x * ve; g_mean.y += dm.y * ve;
        g_conic.a += dcn.a * ve; g_conic.b += dcn.b * ve; g_conic.c += dcn.c * ve;
        abs_c[0] += std::abs(dm.x * ve_c); abs_c[1] += std::abs(dm.y * ve_c);
        abs_g[0] += std::abs(dm.x * ve_g); abs_g[1] += std::abs(dm.y * ve_g);
      }
    }
    T* dst_c = gc_base + C * gid;
    for (int64_t c = 0; c < C; ++c) dst_c[c] += gcol[c];
    T* dst_g = gg_base + G * gid;
    for (int64_t c = 0; c < G; ++c) dst_g[c] += ggeo[c];
    T* gp = gp_base + 8 * gid;
    gp[0] += g_mean.x; gp[1] += g_mean.y;
    gp[2] += g_conic.a; gp[3] += g_conic.b; gp[4] += g_conic.c;
    gp[5] += g_oc; gp[6] += g_og; gp[7] += g_z;
    T* ga = ga_base + 4 * gid;
    ga[0] += abs_c[0]; ga[1] += abs_c[1]; ga[2] += abs_g[0]; ga[3] += abs_g[1];
  }
}

void check_raster_inputs(const at::Tensor& means2d, const at::Tensor& conics,
                         const at::Tensor& opacities, const at::Tensor& depths,
                         const at::Tensor& colors, const at::Tensor& geometry,
                         const at::Tensor& rects, const at::Tensor& tile_offsets,
                         const at::Tensor& flat_ids) {
  const int64_t n = means2d.size(0);
  check_cpu_input(means2d, "means2d", {n, 2});
  check_cpu_input(conics, "conics", {n, 3});
  check_cpu_input(opacities, "opacities", {n, 2});
  check_cpu_input(depths, "depths", {n});
  check_cpu_input(colors, "colors", {n, -1});
  check_cpu_input(geometry, "geometry", {n, -1});
  check_cpu_input(rects, "rects", {n, 4});
  check_cpu_input(tile_offsets, "tile_offsets", {-1});
  check_cpu_input(flat_ids, "flat_ids", {-1});
  check_same_dtype({means2d, conics, opacities, depths, colors, geometry});
  TORCH_CHECK(rects.scalar_type() == at::kInt && flat_ids.scalar_type() == at::kInt,
              "rects and flat_ids must be int32");
  TORCH_CHECK(tile_offsets.scalar_type() == at::kLong, "tile_offsets must be int64");
}

Tiling make_tiling(int64_t width, int64_t height, int64_t tile_size, const at::Tensor& offsets) {
  TORCH_CHECK(tile_size > 0, "tile_size must be positive");
  Tiling t{width, height, tile_size, (width + tile_size - 1) / tile_size,
           (height + tile_size - 1) / tile_size};
  TORCH_CHECK(offsets.size(0) == t.count() + 1, "tile_offsets has ", offsets.size(0),
              " entries, expected ", t.count() + 1);
  return t;
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
rasterize_fwd(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
              const at::Tensor& depths, const at::Tensor& colors, const at::Tensor& geometry,
              const at::Tensor& rects, const at::Tensor& tile_offsets, const at::Tensor& flat_ids,
              int64_t width, int64_t height, int64_t tile_size, bool geometry_branch) {
#ifdef DGS_WITH_CUDA
  if (means2d.is_cuda())
    return rasterize_fwd_cuda(means2d, conics, opacities, depths, colors, geometry, rects,
                              tile_offsets, flat_ids, width, height, tile_size, geometry_branch);
#endif
  check_raster_inputs(means2d, conics, opacities, depths, colors, geometry, rects, tile_offsets,
                      flat_ids);
  const Tiling tl = make_tiling(width, height, tile_size, tile_offsets);
  const int64_t n = means2d.size(0), C = colors.size(1), G = geometry.size(1);
  auto opts = means2d.options();
  at::Tensor out_color = at::zeros({height, width, C}, opts);
  at::Tensor out_geo = at::zeros({height, width, G}, opts);
  at::Tensor out_depth = at::zeros({height, width, 1}, opts);
  at::Tensor trans = at::ones({height, width, 2}, opts);
  at::Tensor stops = at::zeros({height, width, 2}, opts.dtype(at::kInt));
  const int64_t parts = raster_parts(tl);
  at::Tensor contrib = at::zeros({parts, n}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_fwd", [&] {
    using T = scalar_t;
    FwdArgs<T> a{means2d.data_ptr<T>(), conics.data_ptr<T>(), opacities.data_ptr<T>(),
                 depths.data_ptr<T>(), colors.data_ptr<T>(), geometry.data_ptr<T>(),
                 rects.data_ptr<int32_t>(), flat_ids.data_ptr<int32_t>(),
                 tile_offsets.data_ptr<int64_t>(), n, C, G, out_color.data_ptr<T>(),
                 out_geo.data_ptr<T>(), out_depth.data_ptr<T>(), trans.data_ptr<T>(),
                 stops.data_ptr<int32_t>(), contrib.data_ptr<T>(), geometry_branch};
    for_parts(tl, parts, [&](int64_t part, int64_t begin, int64_t end) {
      const int64_t np = tl.size * tl.size;
      std::vector<T> tcs(np), tgs(np);
      std::vector<int32_t> stop_c(np), stop_g(np);
      std::vector<uint8_t> done(np);
      T* my_contrib = a.contrib + part * n;
      for (int64_t t = begin; t < end; ++t)
        forward_tile(a, tl, t, tcs, tgs, stop_c, stop_g, done, my_contrib);
    });
  });
  return {out_color, out_geo, out_depth, trans, stops, std::get<0>(contrib.max(0))};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
rasterize_bwd(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
              const at::Tensor& depths, const at::Tensor& colors, const at::Tensor& geometry,
              const at::Tensor& rects, const at::Tensor& tile_offsets, const at::Tensor& flat_ids,
              int64_t width, int64_t height, int64_t tile_size, bool geometry_branch,
              const at::Tensor& out_color, const at::Tensor& out_geometry,
              const at::Tensor& out_depth, const at::Tensor& transmittance,
              const at::Tensor& stops, const at::Tensor& v_color, const at::Tensor& v_geometry,
              const at::Tensor& v_depth, const at::Tensor& v_alpha) {
#ifdef DGS_WITH_CUDA
  if (means2d.is_cuda())
    return rasterize_bwd_cuda(means2d, conics, opacities, depths, colors, geometry, rects,
                              tile_offsets, flat_ids, width, height, tile_size, geometry_branch,
                              out_color, out_geometry, out_depth, transmittance, stops, v_color,
                              v_geometry, v_depth, v_alpha);
#endif
  check_raster_inputs(means2d, conics, opacities, depths, colors, geometry, rects, tile_offsets,
                      flat_ids);
  const Tiling tl = make_tiling(width, height, tile_size, tile_offsets);
  const int64_t n = means2d.size(0), C = colors.size(1), G = geometry.size(1);
  check_cpu_input(out_color, "out_color", {height, width, C});
  check_cpu_input(out_geometry, "out_geometry", {height, width, G});
  check_cpu_input(out_depth, "out_depth", {height, width, 1});
  check_cpu_input(transmittance, "transmittance", {height, width, 2});
  check_cpu_input(stops, "stops", {height, width, 2});
  check_cpu_input(v_color, "v_color", {height, width, C});
  check_cpu_input(v_geometry, "v_geometry", {height, width, G});
  check_cpu_input(v_depth, "v_depth", {height, width, 1});
  check_cpu_input(v_alpha, "v_alpha", {height, width, 2});
  const int64_t parts = raster_parts(tl);
  auto opts = means2d.options();
  at::Tensor g_param = at::zeros({parts, n, 8}, opts);
  at::Tensor g_abs = at::zeros({parts, n, 4}, opts);
  at::Tensor g_color = at::zeros({parts, n, C}, opts);
  at::Tensor g_geo = at::zeros({parts, n, G}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_bwd", [&] {
    using T = scalar_t;
    BwdArgs<T> a{means2d.data_ptr<T>(), conics.data_ptr<T>(), opacities.data_ptr<T>(),
                 depths.data_ptr<T>(), colors.data_ptr<T>(), geometry.data_ptr<T>(),
                 rects.data_ptr<int32_t>(), flat_ids.data_ptr<int32_t>(),
                 tile_offsets.data_ptr<int64_t>(), n, C, G, out_color.data_ptr<T>(),
                 out_geometry.data_ptr<T>(), out_depth.data_ptr<T>(),
                 transmittance.data_ptr<T>(), stops.data_ptr<int32_t>(), v_color.data_ptr<T>(),
                 v_geometry.data_ptr<T>(), v_depth.data_ptr<T>(), v_alpha.data_ptr<T>(),
                 g_param.data_ptr<T>(), g_abs.data_ptr<T>(), g_color.data_ptr<T>(),
                 g_geo.data_ptr<T>(), geometry_branch};
    for_parts(tl, parts, [&](int64_t part, int64_t begin, int64_t end) {
      const int64_t np = tl.size * tl.size;
      BranchState<T> sc(np), sg(np);
      std::vector<T> acc(C + G);
      for (int64_t t = begin; t < end; ++t) backward_tile(a, tl, t, sc, sg, acc, int(part));
    });
  });
  at::Tensor gp = parts > 1 ? g_param.sum(0) : g_param[0];
  at::Tensor ga = parts > 1 ? g_abs.sum(0) : g_abs[0];
  at::Tensor gc = parts > 1 ? g_color.sum(0) : g_color[0];
  at::Tensor gg = parts > 1 ? g_geo.sum(0) : g_geo[0];
  return {gp.slice(1, 0, 2).contiguous(), gp.slice(1, 2, 5).contiguous(),
          gp.slice(1, 5, 7).contiguous(), gp.select(1, 7).contiguous(), gc, gg, ga};
}

}  // namespace dgs
