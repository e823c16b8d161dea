// Blending of both branches: torch side of the CUDA kernels (rasterize.cu), built only with
// DGS_WITH_CUDA.
#include "checks.h"
#include "cuda_common.h"
#include "rasterize.h"
#include "rasterize_cuda.h"

namespace dgs {
namespace {

void check_raster_inputs_cuda(const at::Tensor& means2d, const at::Tensor& conics,
                              const at::Tensor& opacities, const at::Tensor& depths,
                              const at::Tensor& colors, const at::Tensor& geometry,
                              const at::Tensor& rects, const at::Tensor& tile_offsets,
                              const at::Tensor& flat_ids, int64_t width, int64_t height,
                              int64_t tile_size) {
  const int64_t n = means2d.size(0);
  const at::Device dev = means2d.device();
  check_cuda_input(means2d, "means2d", {n, 2}, dev);
  check_cuda_input(conics, "conics", {n, 3}, dev);
  check_cuda_input(opacities, "opacities", {n, 2}, dev);
  check_cuda_input(depths, "depths", {n}, dev);
  check_cuda_input(colors, "colors", {n, -1}, dev);
  check_cuda_input(geometry, "geometry", {n, -1}, dev);
  check_cuda_input(rects, "rects", {n, 4}, dev);
  check_cuda_input(tile_offsets, "tile_offsets", {-1}, dev);
  check_cuda_input(flat_ids, "flat_ids", {-1}, dev);
  check_same_dtype({means2d, conics, opacities, depths, colors, geometry});
  TORCH_CHECK(rects.scalar_type() == at::kInt && flat_ids.scalar_type() == at::kInt,
              "rects and flat_ids must be int32");
  TORCH_CHECK(tile_offsets.scalar_type() == at::kLong, "tile_offsets must be int64");
  TORCH_CHECK(tile_size > 0 && tile_size <= 16, "tile_size must be in [1, 16] on CUDA, got ",
              tile_size);
  const int64_t n_tiles =
      ((width + tile_size - 1) / tile_size) * ((height + tile_size - 1) / tile_size);
  TORCH_CHECK(tile_offsets.size(0) == n_tiles + 1, "tile_offsets has ", tile_offsets.size(0),
              " entries, expected ", n_tiles + 1);
}

// The forward's inputs, which both passes' parameter structs hold under the same names.
template <typename T, typename Params>
void set_inputs(Params& p, const at::Tensor& means2d, const at::Tensor& conics,
                const at::Tensor& opacities, const at::Tensor& depths, const at::Tensor& colors,
                const at::Tensor& geometry, const at::Tensor& rects,
                const at::Tensor& tile_offsets, const at::Tensor& flat_ids, int64_t width,
                int64_t height, int64_t tile_size, bool geometry_branch) {
  p.means2d = ptr_or_null<T>(means2d);
  p.conics = ptr_or_null<T>(conics);
  p.opacities = ptr_or_null<T>(opacities);
  p.depths = ptr_or_null<T>(depths);
  p.colors = ptr_or_null<T>(colors);
  p.geometry = ptr_or_null<T>(geometry);
  p.rects = ptr_or_null<int32_t>(rects);
  p.tile_offsets = tile_offsets.data_ptr<int64_t>();
  p.flat_ids = ptr_or_null<int32_t>(flat_ids);
  p.n = means2d.size(0);
  p.C = int(colors.size(1));
  p.G = int(geometry.size(1));
  p.width = int(width);
  p.height = int(height);
  p.tile_size = int(tile_size);
  p.geometry_branch = geometry_branch;
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
rasterize_fwd_cuda(const at::Tensor& means2d, const at::Tensor& conics,
                   const at::Tensor& opacities, const at::Tensor& depths,
                   const at::Tensor& colors, const at::Tensor& geometry, const at::Tensor& rects,
                   const at::Tensor& tile_offsets, const at::Tensor& flat_ids, int64_t width,
                   int64_t height, int64_t tile_size, bool geometry_branch) {
  check_raster_inputs_cuda(means2d, conics, opacities, depths, colors, geometry, rects,
                           tile_offsets, flat_ids, width, height, tile_size);
  const c10::cuda::CUDAGuard guard(means2d.device());
  const int64_t n = means2d.size(0), C = colors.size(1), G = geometry.size(1);
  auto opts = means2d.options();
  // The launcher writes every pixel entry and zero-fills `contribution` itself.
  at::Tensor out_color = at::empty({height, width, C}, opts);
  at::Tensor out_geo = at::empty({height, width, G}, opts);
  at::Tensor out_depth = at::empty({height, width, 1}, opts);
  at::Tensor trans = at::empty({height, width, 2}, opts);
  at::Tensor stops = at::empty({height, width, 2}, opts.dtype(at::kInt));
  at::Tensor contrib = at::empty({n}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_fwd_cuda", [&] {
    using T = scalar_t;
    cuda::RasterizeFwdParams<T> p{};
    set_inputs<T>(p, means2d, conics, opacities, depths, colors, geometry, rects, tile_offsets,
                  flat_ids, width, height, tile_size, geometry_branch);
    p.out_color = ptr_or_null<T>(out_color);
    p.out_geometry = ptr_or_null<T>(out_geo);
    p.out_depth = ptr_or_null<T>(out_depth);
    p.transmittance = ptr_or_null<T>(trans);
    p.stops = ptr_or_null<int32_t>(stops);
    p.contribution = ptr_or_null<T>(contrib);
    check_launch(cuda::launch_rasterize_fwd<T>(p, current_stream()), "rasterize_fwd");
  });
  return {out_color, out_geo, out_depth, trans, stops, contrib};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>
rasterize_bwd_cuda(const at::Tensor& means2d, const at::Tensor& conics,
                   const at::Tensor& opacities, const at::Tensor& depths,
                   const at::Tensor& colors, const at::Tensor& geometry, const at::Tensor& rects,
                   const at::Tensor& tile_offsets, const at::Tensor& flat_ids, int64_t width,
                   int64_t height, int64_t tile_size, bool geometry_branch,
                   const at::Tensor& out_color, const at::Tensor& out_geometry,
                   const at::Tensor& out_depth, const at::Tensor& transmittance,
                   const at::Tensor& stops, const at::Tensor& v_color,
                   const at::Tensor& v_geometry, const at::Tensor& v_depth,
                   const at::Tensor& v_alpha) {
  check_raster_inputs_cuda(means2d, conics, opacities, depths, colors, geometry, rects,
                           tile_offsets, flat_ids, width, height, tile_size);
  const int64_t n = means2d.size(0), C = colors.size(1), G = geometry.size(1);
  const at::Device dev = means2d.device();
  check_cuda_input(out_color, "out_color", {height, width, C}, dev);
  check_cuda_input(out_geometry, "out_geometry", {height, width, G}, dev);
  check_cuda_input(out_depth, "out_depth", {height, width, 1}, dev);
  check_cuda_input(transmittance, "transmittance", {height, width, 2}, dev);
  check_cuda_input(stops, "stops", {height, width, 2}, dev);
  check_cuda_input(v_color, "v_color", {height, width, C}, dev);
  check_cuda_input(v_geometry, "v_geometry", {height, width, G}, dev);
  check_cuda_input(v_depth, "v_depth", {height, width, 1}, dev);
  check_cuda_input(v_alpha, "v_alpha", {height, width, 2}, dev);
  check_same_dtype({means2d, out_color, out_geometry, out_depth, transmittance, v_color,
                    v_geometry, v_depth, v_alpha});
  TORCH_CHECK(stops.scalar_type() == at::kInt, "stops must be int32");
  const c10::cuda::CUDAGuard guard(dev);
  auto opts = means2d.options();
  // Zero-filled by the launcher, then accumulated with atomics.
  at::Tensor g_means2d = at::empty({n, 2}, opts);
  at::Tensor g_conics = at::empty({n, 3}, opts);
  at::Tensor g_opac = at::empty({n, 2}, opts);
  at::Tensor g_depths = at::empty({n}, opts);
  at::Tensor g_colors = at::empty({n, C}, opts);
  at::Tensor g_geo = at::empty({n, G}, opts);
  at::Tensor absgrad = at::empty({n, 4}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_bwd_cuda", [&] {
    using T = scalar_t;
    cuda::RasterizeBwdParams<T> p{};
    set_inputs<T>(p, means2d, conics, opacities, depths, colors, geometry, rects, tile_offsets,
                  flat_ids, width, height, tile_size, geometry_branch);
    p.out_color = ptr_or_null<T>(out_color);
    p.out_geometry = ptr_or_null<T>(out_geometry);
    p.out_depth = ptr_or_null<T>(out_depth);
    p.transmittance = ptr_or_null<T>(transmittance);
    p.stops = ptr_or_null<int32_t>(stops);
    p.v_color = ptr_or_null<T>(v_color);
    p.v_geometry = ptr_or_null<T>(v_geometry);
    p.v_depth = ptr_or_null<T>(v_depth);
    p.v_alpha = ptr_or_null<T>(v_alpha);
    p.g_means2d = ptr_or_null<T>(g_means2d);
    p.g_conics = ptr_or_null<T>(g_conics);
    p.g_opacities = ptr_or_null<T>(g_opac);
    p.g_depths = ptr_or_null<T>(g_depths);
    p.g_colors = ptr_or_null<T>(g_colors);
    p.g_geometry = ptr_or_null<T>(g_geo);
    p.absgrad = ptr_or_null<T>(absgrad);
    check_launch(cuda::launch_rasterize_bwd<T>(p, current_stream()), "rasterize_bwd");
  });
  return {g_means2d, g_conics, g_opac, g_depths, g_colors, g_geo, absgrad};
}

}  // namespace dgs
