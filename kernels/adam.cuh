// One AdamW step (Adam with decoupled weight decay, torch.optim.AdamW) on a flat parameter array
// (host/adam.hpp is the spec), step t 1-based and counting this step, all arrays (n):
//   p *= 1 - lr * weight_decay
//   m = beta1 m + (1 - beta1) g                (exp_avg)
//   v = beta2 v + (1 - beta2) g^2              (exp_avg_sq)
//   p -= lr / (1 - beta1^t) * m / (sqrt(v) / sqrt(1 - beta2^t) + eps)
// The scalar coefficients are worked out in double on the host, then each element is updated in
// float, in PyTorch's order. Elementwise: deterministic. Pointers are device memory; the work is
// queued on `stream`.
#pragma once

#include <cstdint>

#include "core/adam_options.hpp"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

using pillarseg::AdamOptions;

// params, exp_avg, exp_avg_sq (n) updated in place from grads (n); step >= 1. The four arrays do
// not overlap.
void adam_step(float* params, const float* grads, float* exp_avg, float* exp_avg_sq, std::int64_t n,
               std::int64_t step, const AdamOptions& options, cudaStream_t stream);

}  // namespace pillarseg::cuda
