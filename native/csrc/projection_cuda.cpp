// Projection: torch side of the CUDA kernels (projection.cu), built only with DGS_WITH_CUDA.
#include "checks.h"
#include "cuda_common.h"
#include "projection.h"
#include "projection_cuda.h"

namespace dgs {
namespace {

void check_projection_inputs(const at::Tensor& means, const at::Tensor& quats,
                             const at::Tensor& scales, const at::Tensor& opacity_c,
                             const at::Tensor& opacity_g, const at::Tensor& viewmat,
                             const at::Tensor& K) {
  const int64_t n = means.size(0);
  const at::Device dev = means.device();
  check_cuda_input(means, "means", {n, 3}, dev);
  check_cuda_input(quats, "quats", {n, 4}, dev);
  check_cuda_input(scales, "scales", {n, 3}, dev);
  check_cuda_input(opacity_c, "opacity_c", {n}, dev);
  check_cuda_input(opacity_g, "opacity_g", {n}, dev);
  check_cuda_input(viewmat, "viewmat", {4, 4}, dev);
  check_cuda_input(K, "K", {3, 3}, dev);
  check_same_dtype({means, quats, scales, opacity_c, opacity_g, viewmat, K});
  TORCH_CHECK(n < (int64_t(1) << 31), "too many Gaussians for the CUDA kernels: ", n);
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
projection_fwd_cuda(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                    const at::Tensor& opacity_c, const at::Tensor& opacity_g,
                    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
                    double beta, double eps2d, bool antialiased, double near_plane,
                    double far_plane) {
  check_projection_inputs(means, quats, scales, opacity_c, opacity_g, viewmat, K);
  const c10::cuda::CUDAGuard guard(means.device());
  const int64_t n = means.size(0);
  auto opts = means.options();
  // The launcher writes every entry.
  at::Tensor means2d = at::empty({n, 2}, opts);
  at::Tensor conics = at::empty({n, 3}, opts);
  at::Tensor depths = at::empty({n}, opts);
  at::Tensor opac = at::empty({n, 2}, opts);
  at::Tensor rects = at::empty({n, 4}, opts.dtype(at::kInt));
  at::Tensor radii = at::empty({n}, opts.dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "projection_fwd_cuda", [&] {
    using T = scalar_t;
    check_launch(cuda::launch_projection_fwd<T>(
                     means.data_ptr<T>(), quats.data_ptr<T>(), scales.data_ptr<T>(),
                     opacity_c.data_ptr<T>(), opacity_g.data_ptr<T>(), viewmat.data_ptr<T>(),
                     K.data_ptr<T>(), n, int(width), int(height), T(beta), T(eps2d),
                     antialiased, T(near_plane), T(far_plane), means2d.data_ptr<T>(),
                     conics.data_ptr<T>(), depths.data_ptr<T>(), opac.data_ptr<T>(),
                     rects.data_ptr<int32_t>(), radii.data_ptr<int32_t>(), current_stream()),
                 "projection_fwd");
  });
  return {means2d, conics, depths, opac, rects, radii};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
projection_bwd_cuda(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                    const at::Tensor& opacity_c, const at::Tensor& opacity_g,
                    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
                    double beta, double eps2d, bool antialiased, double near_plane,
                    double far_plane, const at::Tensor& v_means2d, const at::Tensor& v_conics,
                    const at::Tensor& v_depths, const at::Tensor& v_opacities) {
  check_projection_inputs(means, quats, scales, opacity_c, opacity_g, viewmat, K);
  const int64_t n = means.size(0);
  const at::Device dev = means.device();
  check_cuda_input(v_means2d, "v_means2d", {n, 2}, dev);
  check_cuda_input(v_conics, "v_conics", {n, 3}, dev);
  check_cuda_input(v_depths, "v_depths", {n}, dev);
  check_cuda_input(v_opacities, "v_opacities", {n, 2}, dev);
  check_same_dtype({means, v_means2d, v_conics, v_depths, v_opacities});
  const c10::cuda::CUDAGuard guard(dev);
  auto opts = means.options();
  // Per-Gaussian gradients are written for every entry; g_viewmat and g_K are zero-filled by
  // the launcher before the blocks add into them.
  at::Tensor g_means = at::empty({n, 3}, opts);
  at::Tensor g_quats = at::empty({n, 4}, opts);
  at::Tensor g_scales = at::empty({n, 3}, opts);
  at::Tensor g_op_c = at::empty({n}, opts);
  at::Tensor g_op_g = at::empty({n}, opts);
  at::Tensor g_viewmat = at::empty({4, 4}, opts);
  at::Tensor g_K = at::empty({3, 3}, opts);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "projection_bwd_cuda", [&] {
    using T = scalar_t;
    check_launch(cuda::launch_projection_bwd<T>(
                     means.data_ptr<T>(), quats.data_ptr<T>(), scales.data_ptr<T>(),
                     opacity_c.data_ptr<T>(), opacity_g.data_ptr<T>(), viewmat.data_ptr<T>(),
                     K.data_ptr<T>(), n, int(width), int(height), T(beta), T(eps2d),
                     antialiased, T(near_plane), T(far_plane), v_means2d.data_ptr<T>(),
                     v_conics.data_ptr<T>(), v_depths.data_ptr<T>(), v_opacities.data_ptr<T>(),
                     g_means.data_ptr<T>(), g_quats.data_ptr<T>(), g_scales.data_ptr<T>(),
                     g_op_c.data_ptr<T>(), g_op_g.data_ptr<T>(), g_viewmat.data_ptr<T>(),
                     g_K.data_ptr<T>(), current_stream()),
                 "projection_bwd");
  });
  return {g_means, g_quats, g_scales, g_op_c, g_op_g, g_viewmat, g_K};
}

}  // namespace dgs
