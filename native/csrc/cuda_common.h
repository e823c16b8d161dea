// Torch-side helpers shared by the CUDA wrappers (<op>_cuda.cpp), compiled only with
// DGS_WITH_CUDA. The kernels themselves (<op>.cu) never include torch.
#pragma once

#include <c10/cuda/CUDAStream.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/extension.h>

namespace dgs {

// The stream the kernels run on: torch's current stream of the inputs' device, so they order
// with the surrounding torch work and the caching allocator's reuse.
inline cudaStream_t current_stream() { return c10::cuda::getCurrentCUDAStream().stream(); }

// A launcher's status as a torch error naming the op (launch failures surface here; faults
// inside a kernel surface at the next synchronizing call).
inline void check_launch(cudaError_t status, const char* op) {
  TORCH_CHECK(status == cudaSuccess, op, " (CUDA) failed: ", cudaGetErrorString(status));
}

template <typename T> T* ptr_or_null(const at::Tensor& t) {
  return t.numel() ? t.data_ptr<T>() : nullptr;
}

}  // namespace dgs
