// Gaussian ray tracer on the CPU: the BVH of raytrace_bvh.h (binned SAH, built on the host),
// traversal with an explicit stack, parallel over origins.
#include "raytrace.h"

#include <ATen/Parallel.h>

#include "checks.h"
#include "raytrace_bvh.h"

namespace dgs {

at::Tensor trace_visibility(const at::Tensor& origins, const at::Tensor& normals,
                            const at::Tensor& means, const at::Tensor& quats,
                            const at::Tensor& scales, const at::Tensor& opacity,
                            const at::Tensor& exclude, int64_t n_dirs) {
#ifdef DGS_WITH_CUDA
  if (origins.is_cuda())
    return trace_visibility_cuda(origins, normals, means, quats, scales, opacity, exclude,
                                 n_dirs);
#endif
  const int64_t m = origins.size(0), n = means.size(0);
  check_cpu_input(origins, "origins", {m, 3});
  check_cpu_input(normals, "normals", {m, 3});
  check_cpu_input(means, "means", {n, 3});
  check_cpu_input(quats, "quats", {n, 4});
  check_cpu_input(scales, "scales", {n, 3});
  check_cpu_input(opacity, "opacity", {n});
  check_cpu_input(exclude, "exclude", {m});
  check_same_dtype({origins, normals, means, quats, scales, opacity});
  TORCH_CHECK(exclude.scalar_type() == at::kLong, "exclude must be int64");
  TORCH_CHECK(n_dirs > 0 && n_dirs < (int64_t(1) << 31), "n_dirs must be in [1, 2^31), got ",
              n_dirs);
  TORCH_CHECK(n < (int64_t(1) << 31), "too many Gaussians for the CPU tracer: ", n);
  at::Tensor vis = at::ones({m}, origins.options());
  if (n == 0 || m == 0) return vis;
  AT_DISPATCH_FLOATING_TYPES(origins.scalar_type(), "trace_visibility", [&] {
    using T = scalar_t;
    const auto parallel = [](int64_t size, int64_t grain, const auto& body) {
      at::parallel_for(0, size, grain, body);
    };
    const BvhArrays<T> g = build_bvh<T>(means.data_ptr<T>(), quats.data_ptr<T>(),
                                        scales.data_ptr<T>(), opacity.data_ptr<T>(), n, parallel);
    const BvhView<T> bvh = g.view();
    const T* op = origins.data_ptr<T>();
    const T* np = normals.data_ptr<T>();
    const int64_t* ex = exclude.data_ptr<int64_t>();
    T* out = vis.data_ptr<T>();
    at::parallel_for(0, m, 64, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i)
        out[i] = origin_visibility(bvh, op + 3 * i, np + 3 * i, ex[i], int(n_dirs));
    });
  });
  return vis;
}

}  // namespace dgs
