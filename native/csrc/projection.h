// Projection of 3D Gaussians to the image: EWA covariance, Mip-Splatting compensation, beta
// mixing of the two opacities, screen rectangle. One thread of work per Gaussian.
#pragma once

#include <ATen/ATen.h>

#include <tuple>

namespace dgs {

// Returns means2d (N,2), conics (N,3), depths (N), opacities (N,2) [appearance, geometry],
// rects (N,4) int32 inclusive pixel box (u0, v0, u1, v1), radii (N) int32 (0 = not drawn).
// Gaussians outside (near, far) or with a degenerate 2D covariance get zeros everywhere.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
projection_fwd(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
               const at::Tensor& opacity_c, const at::Tensor& opacity_g, const at::Tensor& viewmat,
               const at::Tensor& K, int64_t width, int64_t height, double beta, double eps2d,
               bool antialiased, double near_plane, double far_plane);

// Returns gradients for means, quats, scales, opacity_c, opacity_g, viewmat, K.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
projection_bwd(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
               const at::Tensor& opacity_c, const at::Tensor& opacity_g, const at::Tensor& viewmat,
               const at::Tensor& K, int64_t width, int64_t height, double beta, double eps2d,
               bool antialiased, double near_plane, double far_plane,
               const at::Tensor& v_means2d, const at::Tensor& v_conics,
               const at::Tensor& v_depths, const at::Tensor& v_opacities);

#ifdef DGS_WITH_CUDA
// The same ops on CUDA tensors (projection_cuda.cpp); the functions above call them for CUDA
// inputs.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
projection_fwd_cuda(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                    const at::Tensor& opacity_c, const at::Tensor& opacity_g,
                    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
                    double beta, double eps2d, bool antialiased, double near_plane,
                    double far_plane);

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
projection_bwd_cuda(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                    const at::Tensor& opacity_c, const at::Tensor& opacity_g,
                    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
                    double beta, double eps2d, bool antialiased, double near_plane,
                    double far_plane, const at::Tensor& v_means2d, const at::Tensor& v_conics,
                    const at::Tensor& v_depths, const at::Tensor& v_opacities);
#endif

}  // namespace dgs
