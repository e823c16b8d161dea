// Projection: torch side and CPU kernel. The per-Gaussian math is in gaussian_math.h.
#include "projection.h"

#include <ATen/Parallel.h>

#include <vector>

#include "checks.h"
#include "gaussian_math.h"

namespace dgs {
namespace {

template <typename T> ProjCamera<T> read_camera(const at::Tensor& viewmat, const at::Tensor& K,
                                                int64_t width, int64_t height) {
  return camera_from(viewmat.data_ptr<T>(), K.data_ptr<T>(), int(width), int(height));
}

template <typename T>
void projection_fwd_kernel(const at::Tensor& means, const at::Tensor& quats,
                           const at::Tensor& scales, const at::Tensor& opacity_c,
                           const at::Tensor& opacity_g, const ProjCamera<T>& cam, T beta, T eps2d,
                           bool antialiased, T near_plane, T far_plane, at::Tensor& means2d,
                           at::Tensor& conics, at::Tensor& depths, at::Tensor& opac,
                           at::Tensor& rects, at::Tensor& radii) {
  const T* mp = means.data_ptr<T>();
  const T* qp = quats.data_ptr<T>();
  const T* sp = scales.data_ptr<T>();
  const T* ocp = opacity_c.data_ptr<T>();
  const T* ogp = opacity_g.data_ptr<T>();
  T* m2 = means2d.data_ptr<T>();
  T* cn = conics.data_ptr<T>();
  T* dp = depths.data_ptr<T>();
  T* op = opac.data_ptr<T>();
  int32_t* rc = rects.data_ptr<int32_t>();
  int32_t* rd = radii.data_ptr<int32_t>();
  const int64_t n = means.size(0);
  at::parallel_for(0, n, 2048, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      rc[4 * i] = 0; rc[4 * i + 1] = 0; rc[4 * i + 2] = -1; rc[4 * i + 3] = -1;
      rd[i] = 0;
      const Projected<T> g =
          project_one(mp + 3 * i, qp + 4 * i, sp + 3 * i, cam, eps2d, antialiased, near_plane,
                      far_plane);
      if (!g.valid) continue;
      // Every Gaussian in front of the camera gets its projected values (they are outputs and
      // differentiable); only those that can reach 1/255 inside the image get a rectangle.
      T o_c, o_g;
      mix_opacities(ocp[i], ogp[i], beta, g.comp, o_c, o_g);
      const T mx = cam.k.fx * g.p.x / g.p.z + cam.k.cx;
      const T my = cam.k.fy * g.p.y / g.p.z + cam.k.cy;
      const Sym2<T> conic = inverse2(g.cov2d);
      m2[2 * i] = mx; m2[2 * i + 1] = my;
      cn[3 * i] = conic.a; cn[3 * i + 1] = conic.b; cn[3 * i + 2] = conic.c;
      dp[i] = g.p.z;
      op[2 * i] = o_c; op[2 * i + 1] = o_g;
      T ex, ey;
      if (!screen_extent(g.cov2d, o_c > o_g ? o_c : o_g, ex, ey)) continue;
      int32_t rect[4];
      if (!pixel_rect(mx, my, ex, ey, cam.k.width, cam.k.height, rect)) continue;
      for (int j = 0; j < 4; ++j) rc[4 * i + j] = rect[j];
      const T r = m_ceil(ex > ey ? ex : ey);
      rd[i] = r < T(1) ? 1 : int32_t(r);
    }
  });
}

template <typename T>
void projection_bwd_kernel(const at::Tensor& means, const at::Tensor& quats,
                           const at::Tensor& scales, const at::Tensor& opacity_c,
                           const at::Tensor& opacity_g, const ProjCamera<T>& cam, T beta, T eps2d,
                           bool antialiased, T near_plane, T far_plane, const at::Tensor& v_means2d,
                           const at::Tensor& v_conics, const at::Tensor& v_depths,
                           const at::Tensor& v_opac, at::Tensor& g_means, at::Tensor& g_quats,
                           at::Tensor& g_scales, at::Tensor& g_op_c, at::Tensor& g_op_g,
                           std::vector<T>& cam_grad, int nthreads) {
  const T* mp = means.data_ptr<T>();
  const T* qp = quats.data_ptr<T>();
  const T* sp = scales.data_ptr<T>();
  const T* ocp = opacity_c.data_ptr<T>();
  const T* ogp = opacity_g.data_ptr<T>();
  const T* vm2 = v_means2d.data_ptr<T>();
  const T* vcn = v_conics.data_ptr<T>();
  const T* vdp = v_depths.data_ptr<T>();
  const T* vop = v_opac.data_ptr<T>();
  T* gm = g_means.data_ptr<T>();
  T* gq = g_quats.data_ptr<T>();
  T* gs = g_scales.data_ptr<T>();
  T* goc = g_op_c.data_ptr<T>();
  T* gog = g_op_g.data_ptr<T>();
  const int64_t n = means.size(0);
  // 16 camera gradient entries per thread: rotation (9), translation (3), fx fy cx cy (4).
  cam_grad.assign(size_t(nthreads) * 16, T(0));
  at::parallel_for(0, n, 2048, [&](int64_t begin, int64_t end) {
    T local[16] = {};
    for (int64_t i = begin; i < end; ++i) {
      const Projected<T> g = project_one(mp + 3 * i, qp + 4 * i, sp + 3 * i, cam, eps2d,
                                         antialiased, near_plane, far_plane);
      if (!g.valid) continue;
      const ProjectionGrads<T> pg = project_one_vjp(
          g, mp + 3 * i, qp + 4 * i, sp + 3 * i, ocp[i], ogp[i], cam, beta, eps2d, antialiased,
          vm2 + 2 * i, vcn + 3 * i, vdp[i], vop + 2 * i);
      for (int j = 0; j < 3; ++j) gm[3 * i + j] = pg.mean[j];
      for (int j = 0; j < 4; ++j) gq[4 * i + j] = pg.quat[j];
      for (int j = 0; j < 3; ++j) gs[3 * i + j] = pg.scale[j];
      goc[i] = pg.op_c;
      gog[i] = pg.op_g;
      for (int j = 0; j < 16; ++j) local[j] += pg.camera[j];
    }
    T* dst = cam_grad.data() + 16 * at::get_thread_num();
    for (int j = 0; j < 16; ++j) dst[j] += local[j];
  });
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
projection_fwd(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
               const at::Tensor& opacity_c, const at::Tensor& opacity_g, const at::Tensor& viewmat,
               const at::Tensor& K, int64_t width, int64_t height, double beta, double eps2d,
               bool antialiased, double near_plane, double far_plane) {
#ifdef DGS_WITH_CUDA
  if (means.is_cuda())
    return projection_fwd_cuda(means, quats, scales, opacity_c, opacity_g, viewmat, K, width,
                               height, beta, eps2d, antialiased, near_plane, far_plane);
#endif
  const int64_t n = means.size(0);
  check_cpu_input(means, "means", {n, 3});
  check_cpu_input(quats, "quats", {n, 4});
  check_cpu_input(scales, "scales", {n, 3});
  check_cpu_input(opacity_c, "opacity_c", {n});
  check_cpu_input(opacity_g, "opacity_g", {n});
  check_cpu_input(viewmat, "viewmat", {4, 4});
  check_cpu_input(K, "K", {3, 3});
  check_same_dtype({means, quats, scales, opacity_c, opacity_g, viewmat, K});
  auto opts = means.options();
  at::Tensor means2d = at::zeros({n, 2}, opts);
  at::Tensor conics = at::zeros({n, 3}, opts);
  at::Tensor depths = at::zeros({n}, opts);
  at::Tensor opac = at::zeros({n, 2}, opts);
  at::Tensor rects = at::empty({n, 4}, opts.dtype(at::kInt));
  at::Tensor radii = at::empty({n}, opts.dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "projection_fwd", [&] {
    const ProjCamera<scalar_t> cam = read_camera<scalar_t>(viewmat, K, width, height);
    projection_fwd_kernel<scalar_t>(means, quats, scales, opacity_c, opacity_g, cam,
                                    scalar_t(beta), scalar_t(eps2d), antialiased,
                                    scalar_t(near_plane), scalar_t(far_plane), means2d, conics,
                                    depths, opac, rects, radii);
  });
  return {means2d, conics, depths, opac, rects, radii};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
projection_bwd(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
               const at::Tensor& opacity_c, const at::Tensor& opacity_g, const at::Tensor& viewmat,
               const at::Tensor& K, int64_t width, int64_t height, double beta, double eps2d,
               bool antialiased, double near_plane, double far_plane,
               const at::Tensor& v_means2d, const at::Tensor& v_conics,
               const at::Tensor& v_depths, const at::Tensor& v_opacities) {
#ifdef DGS_WITH_CUDA
  if (means.is_cuda())
    return projection_bwd_cuda(means, quats, scales, opacity_c, opacity_g, viewmat, K, width,
                               height, beta, eps2d, antialiased, near_plane, far_plane,
                               v_means2d, v_conics, v_depths, v_opacities);
#endif
  const int64_t n = means.size(0);
  check_cpu_input(v_means2d, "v_means2d", {n, 2});
  check_cpu_input(v_conics, "v_conics", {n, 3});
  check_cpu_input(v_depths, "v_depths", {n});
  check_cpu_input(v_opacities, "v_opacities", {n, 2});
  check_cpu_input(viewmat, "viewmat", {4, 4});
  check_cpu_input(K, "K", {3, 3});
  auto opts = means.options();
  at::Tensor g_means = at::zeros({n, 3}, opts);
  at::Tensor g_quats = at::zeros({n, 4}, opts);
  at::Tensor g_scales = at::zeros({n, 3}, opts);
  at::Tensor g_op_c = at::zeros({n}, opts);
  at::Tensor g_op_g = at::zeros({n}, opts);
  at::Tensor g_viewmat = at::zeros({4, 4}, opts);
  at::Tensor g_K = at::zeros({3, 3}, opts);
  const int nthreads = at::get_num_threads();
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "projection_bwd", [&] {
    const ProjCamera<scalar_t> cam = read_camera<scalar_t>(viewmat, K, width, height);
    std::vector<scalar_t> cam_grad;
    projection_bwd_kernel<scalar_t>(means, quats, scales, opacity_c, opacity_g, cam,
                                    scalar_t(beta), scalar_t(eps2d), antialiased,
                                    scalar_t(near_plane), scalar_t(far_plane), v_means2d, v_conics, v_depths, v_opacities, g_means, g_quats,
                                    g_scales, g_op_c, g_op_g, cam_grad, nthreads);
    scalar_t total[16] = {};
    for (int t = 0; t < nthreads; ++t)
      for (int j = 0; j < 16; ++j) total[j] += cam_grad[16 * t + j];
    auto gv = g_viewmat.accessor<scalar_t, 2>();
    for (int a = 0; a < 3; ++a) {
      for (int b = 0; b < 3; ++b) gv[a][b] = total[3 * a + b];
      gv[a][3] = total[9 + a];
    }
    auto gk = g_K.accessor<scalar_t, 2>();
    gk[0][0] = total[12]; gk[1][1] = total[13]; gk[0][2] = total[14]; gk[1][2] = total[15];
  });
  return {g_means, g_quats, g_scales, g_op_c, g_op_g, g_viewmat, g_K};
}

}  // namespace dgs
