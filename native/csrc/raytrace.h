// Gaussian ray tracer for ambient occlusion: a BVH over the Gaussians' 3-sigma boxes and rays
// over a Fibonacci hemisphere about a normal; visibility is the cosine-weighted mean of the
// transmittance T = prod (1 - alpha at each Gaussian's closest approach).
#pragma once

#include <ATen/ATen.h>

namespace dgs {

// origins (M,3), normals (M,3) unit; means (N,3), quats (N,4), scales (N,3), opacity (N);
// exclude (M,) int64: a Gaussian index each origin ignores (itself), or -1.
// Returns visibility (M,) in [0, 1].
at::Tensor trace_visibility(const at::Tensor& origins, const at::Tensor& normals,
                            const at::Tensor& means, const at::Tensor& quats,
                            const at::Tensor& scales, const at::Tensor& opacity,
                            const at::Tensor& exclude, int64_t n_dirs);

#ifdef DGS_WITH_CUDA
// The same op on CUDA tensors (raytrace_cuda.cpp): the tree is built on the host from copies of
// the Gaussians, the rays are traced on the inputs' device, and the result stays there.
at::Tensor trace_visibility_cuda(const at::Tensor& origins, const at::Tensor& normals,
                                 const at::Tensor& means, const at::Tensor& quats,
                                 const at::Tensor& scales, const at::Tensor& opacity,
                                 const at::Tensor& exclude, int64_t n_dirs);
#endif

}  // namespace dgs
