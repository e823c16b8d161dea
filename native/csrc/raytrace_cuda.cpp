// Ray tracer: torch side of the CUDA kernel (raytrace.cu), built only with DGS_WITH_CUDA. The
// tree is built on the host by the CPU op's builder (raytrace_bvh.h) from copies of the
// Gaussians; its flat arrays go to the device and the rays are traced there.
#include <ATen/Parallel.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>  // what at::cuda::getCurrentCUDAStream is, without cuSPARSE

#include <vector>

#include "checks.h"
#include "raytrace.h"
#include "raytrace_bvh.h"
#include "raytrace_cuda.h"

namespace dgs {
namespace {

// A host array as a tensor on `device` (a synchronous copy: `v` may be freed after the call).
template <typename E>
at::Tensor to_device(const std::vector<E>& v, at::ScalarType dtype, const at::Device& device) {
  const int64_t bytes = int64_t(v.size() * sizeof(E));
  const at::Tensor host = at::from_blob(const_cast<E*>(v.data()), {bytes},
                                        at::TensorOptions().dtype(at::kByte));
  return host.to(device).view(dtype);
}

}  // namespace

at::Tensor trace_visibility_cuda(const at::Tensor& origins, const at::Tensor& normals,
                                 const at::Tensor& means, const at::Tensor& quats,
                                 const at::Tensor& scales, const at::Tensor& opacity,
                                 const at::Tensor& exclude, int64_t n_dirs) {
  const int64_t m = origins.size(0), n = means.size(0);
  const at::Device device = origins.device();
  check_cuda_input(origins, "origins", {m, 3}, device);
  check_cuda_input(normals, "normals", {m, 3}, device);
  check_cuda_input(means, "means", {n, 3}, device);
  check_cuda_input(quats, "quats", {n, 4}, device);
  check_cuda_input(scales, "scales", {n, 3}, device);
  check_cuda_input(opacity, "opacity", {n}, device);
  check_cuda_input(exclude, "exclude", {m}, device);
  check_same_dtype({origins, normals, means, quats, scales, opacity});
  TORCH_CHECK(exclude.scalar_type() == at::kLong, "exclude must be int64");
  TORCH_CHECK(n_dirs > 0 && n_dirs < (int64_t(1) << 31), "n_dirs must be in [1, 2^31), got ",
              n_dirs);
  TORCH_CHECK(n < (int64_t(1) << 31), "too many Gaussians for the CUDA tracer: ", n);
  const c10::cuda::CUDAGuard guard(device);
  if (n == 0 || m == 0) return at::ones({m}, origins.options());
  at::Tensor vis = at::empty({m}, origins.options());  // the launcher writes every entry
  AT_DISPATCH_FLOATING_TYPES(origins.scalar_type(), "trace_visibility_cuda", [&] {
    using T = scalar_t;
    const at::Tensor h_means = means.cpu(), h_quats = quats.cpu(), h_scales = scales.cpu(),
                     h_opacity = opacity.cpu();
    const auto parallel = [](int64_t size, int64_t grain, const auto& body) {
      at::parallel_for(0, size, grain, body);
    };
    const BvhArrays<T> g = build_bvh<T>(h_means.data_ptr<T>(), h_quats.data_ptr<T>(),
                                        h_scales.data_ptr<T>(), h_opacity.data_ptr<T>(), n,
                                        parallel);
    // Nodes and prims travel as raw bytes: Node<T> and Prim<T> have one layout on the host and
    // the device.
    const at::Tensor d_nodes = to_device(g.nodes, at::kByte, device);
    const at::Tensor d_order = to_device(g.order, at::kInt, device);
    const at::Tensor d_prims = to_device(g.prims, at::kByte, device);
    const BvhView<T> bvh = {reinterpret_cast<const Node<T>*>(d_nodes.data_ptr<uint8_t>()),
                            d_order.data_ptr<int32_t>(),
                            reinterpret_cast<const Prim<T>*>(d_prims.data_ptr<uint8_t>()),
                            g.traced()};
    // The device arrays are freed when this scope ends, before the kernel has run: the caching
    // allocator hands their memory out again only to work queued after it on this stream.
    C10_CUDA_CHECK(cuda::launch_trace_visibility<T>(
        origins.data_ptr<T>(), normals.data_ptr<T>(), exclude.data_ptr<int64_t>(), m, bvh,
        int(n_dirs), vis.data_ptr<T>(), c10::cuda::getCurrentCUDAStream().stream()));
  });
  return vis;
}

}  // namespace dgs
