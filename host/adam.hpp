// Optimiser step and gradient clipping on flat parameter arrays (PyTorch semantics):
//   adam_step:      one torch.optim.AdamW step (Adam with decoupled weight decay);
//   grad_norm:      the L2 norm over all gradient arrays together;
//   clip_grad_norm: torch.nn.utils.clip_grad_norm_ with the L2 norm.
// Call as adam_step<float>(...) / clip_grad_norm<float>(...): T is not deduced through spans.
#pragma once

#include <cstdint>
#include <span>

#include "core/adam_options.hpp"

namespace pillarseg::host {

using pillarseg::AdamOptions;

// One step t (1-based, counting this step) on n parameters; all four spans have length n:
//   p *= 1 - lr * wd
//   m = beta1 * m + (1 - beta1) * g          (exp_avg)
//   v = beta2 * v + (1 - beta2) * g^2        (exp_avg_sq)
//   p -= lr * (m / (1 - beta1^t)) / (sqrt(v / (1 - beta2^t)) + eps)
// beta1 may change from step to step (one-cycle momentum); the bias correction uses the
// current beta1, as PyTorch does when a scheduler rewrites it.
template <class T>
void adam_step(std::span<T> params, std::span<const T> grads, std::span<T> exp_avg,
               std::span<T> exp_avg_sq, int64_t step, const AdamOptions& options);

// sqrt of the sum of g^2 over every element of every array, accumulated in double.
template <class T>
double grad_norm(std::span<const std::span<T>> grads);

// The factor clip_grad_norm_ scales gradients of L2 norm `norm` by for a threshold max_norm > 0:
// max_norm / (norm + 1e-6) where that is below 1, else 1 (no clipping). The one rule of gradient
// clipping: clip_grad_norm below and the trainer's clipping of the backend's flat gradient array
// (engine/train/trainer.cpp) both take it.
double clip_coefficient(double norm, double max_norm);

// Scales every gradient by clip_coefficient(norm, max_norm), so that the norm becomes at most
// max_norm; returns the norm before clipping. A non-finite norm leaves the gradients as they are
// (the caller stops on it).
template <class T>
double clip_grad_norm(std::span<const std::span<T>> grads, double max_norm);

}  // namespace pillarseg::host
