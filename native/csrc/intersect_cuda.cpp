// Tile binning: torch side of the CUDA kernels (intersect.cu), built only with DGS_WITH_CUDA.
// Scratch memory comes from torch's caching allocator as byte tensors.
#include "checks.h"
#include "cuda_common.h"
#include "intersect.h"
#include "intersect_cuda.h"

namespace dgs {

std::tuple<at::Tensor, at::Tensor> intersect_tiles_cuda(const at::Tensor& rects,
                                                        const at::Tensor& depths, int64_t width,
                                                        int64_t height, int64_t tile_size) {
  const int64_t n = rects.size(0);
  const at::Device dev = rects.device();
  check_cuda_input(rects, "rects", {n, 4}, dev);
  check_cuda_input(depths, "depths", {n}, dev);
  TORCH_CHECK(rects.scalar_type() == at::kInt, "rects must be int32");
  TORCH_CHECK(depths.scalar_type() == at::kFloat || depths.scalar_type() == at::kDouble,
              "depths must be float32 or float64");
  TORCH_CHECK(tile_size > 0, "tile_size must be positive");
  TORCH_CHECK(n < (int64_t(1) << 31), "too many Gaussians for the CUDA kernels: ", n);
  const c10::cuda::CUDAGuard guard(dev);
  const cudaStream_t stream = current_stream();
  const int64_t n_tiles =
      ((width + tile_size - 1) / tile_size) * ((height + tile_size - 1) / tile_size);
  auto bytes = rects.options().dtype(at::kByte);
  at::Tensor cum = at::empty({n}, rects.options().dtype(at::kLong));
  int64_t m = 0;
  if (n > 0) {
    const size_t t1 = cuda::intersect_count_temp_bytes(n);
    at::Tensor temp1 = at::empty({int64_t(t1)}, bytes);
    check_launch(cuda::launch_intersect_count(rects.data_ptr<int32_t>(), n, int(width),
                                              int(height), int(tile_size), cum.data_ptr<int64_t>(),
                                              temp1.data_ptr(), t1, stream),
                 "intersect_count");
    m = cum[n - 1].item<int64_t>();  // the pipeline's one device-to-host copy
  }
  at::Tensor offsets = at::empty({n_tiles + 1}, rects.options().dtype(at::kLong));
  at::Tensor ids = at::empty({m}, rects.options());
  const size_t t2 = cuda::intersect_sort_temp_bytes(m, int(width), int(height), int(tile_size));
  at::Tensor temp2 = at::empty({int64_t(t2)}, bytes);
  AT_DISPATCH_FLOATING_TYPES(depths.scalar_type(), "intersect_tiles_cuda", [&] {
    check_launch(cuda::launch_intersect_sort<scalar_t>(
                     rects.data_ptr<int32_t>(), ptr_or_null<scalar_t>(depths),
                     n ? cum.data_ptr<int64_t>() : nullptr, n, m, int(width), int(height),
                     int(tile_size), offsets.data_ptr<int64_t>(), ptr_or_null<int32_t>(ids),
                     t2 ? temp2.data_ptr() : nullptr, t2, stream),
                 "intersect_sort");
  });
  return {offsets, ids};
}

}  // namespace dgs
