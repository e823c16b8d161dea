// Argument checks for the native ops. The public Python function validates first and raises
// ValueError naming the argument; these TORCH_CHECKs guard direct calls into the extension.
#pragma once

#include <ATen/ATen.h>

#include <initializer_list>
#include <vector>

namespace dgs {

inline void check_shape(const at::Tensor& t, const char* name,
                        std::initializer_list<int64_t> shape) {
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  TORCH_CHECK(t.dim() == int64_t(shape.size()), name, " must have ", shape.size(),
              " dimensions, got shape ", t.sizes());
  int64_t d = 0;
  for (int64_t s : shape) {
    TORCH_CHECK(s < 0 || t.size(d) == s, name, " has shape ", t.sizes(), ", expected size ", s,
                " in dimension ", d);
    ++d;
  }
}

inline void check_cpu_input(const at::Tensor& t, const char* name,
                            std::initializer_list<int64_t> shape) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor, got ", t.device());
  check_shape(t, name, shape);
}

// The CUDA ops' twin: every tensor on `device` (the first input's), which must be a GPU.
inline void check_cuda_input(const at::Tensor& t, const char* name,
                             std::initializer_list<int64_t> shape, const at::Device& device) {
  TORCH_CHECK(t.device() == device && device.is_cuda(), name, " must be on ", device, ", got ",
              t.device());
  check_shape(t, name, shape);
}

inline void check_same_dtype(std::initializer_list<at::Tensor> ts) {
  const auto dt = ts.begin()->scalar_type();
  TORCH_CHECK(dt == at::kFloat || dt == at::kDouble, "inputs must be float32 or float64, got ",
              dt);
  for (const auto& t : ts)
    TORCH_CHECK(t.scalar_type() == dt, "all floating inputs must share one dtype (", dt,
                "), got ", t.scalar_type());
}

}  // namespace dgs
