// ReLU on flat float arrays, all of n elements: forward y = relu(x) = (x <= 0 ? 0 : x), backward
// dx = (x <= 0 ? 0 : dy). NaN in x passes through both, as in PyTorch's relu and
// threshold_backward (only x <= 0 is cut). y may be x, and dx may be dy (in place); no other
// overlap. Pointers are device memory; the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// x (n) -> y (n).
void relu_forward(const float* x, float* y, std::int64_t n, cudaStream_t stream);

// x (n), dy (n) -> dx (n).
void relu_backward(const float* x, const float* dy, float* dx, std::int64_t n, cudaStream_t stream);

}  // namespace pillarseg::cuda
