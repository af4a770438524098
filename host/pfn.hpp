// PointPillars PFN layer (OpenPCDet PFNLayer, use_norm, last layer), forward and backward:
//   input (P, N, D) decorated points, D = 10; padding slots are all-zero rows
//   z = input . weight^T                  (P * N, C), weight (C, D), no bias
//   a = ReLU(BatchNorm1d(z))              statistics over all P * N rows, padding included
//   out(p, c) = max over the N slots of a (P, C)
// BatchNorm has PyTorch semantics (see batchnorm.hpp); the PFN's eps and momentum are
// 1e-3 and 0.01.
#pragma once

#include <cstdint>

#include "core/tensor.hpp"
#include "host/batchnorm.hpp"

namespace pillarseg::host {

inline constexpr BatchNormOptions kPfnNormOptions{.eps = 1e-3, .momentum = 0.01};

// What the training forward keeps for the backward.
template <class T>
struct PfnSaved {
  BatchNormSaved<T> norm;  // batch statistics of z (C)
  // (P, C): the slot whose activation is out(p, c), the first of equal ones (torch.max), or -1
  // when out(p, c) is not > 0 (the ReLU's 0, or NaN), where no gradient passes.
  Tensor<int32_t> max_slot;
};

// Training forward. input (P, N, D); weight (C, D); gamma, beta (C); running_mean, running_var
// (C) and num_batches_tracked updated in place as BatchNorm does. Writes out (P, C) and saved.
// P = 0 gives an empty out and leaves the running statistics as they are (no batch to measure).
// scratch: room for P * N * C values (the activations before the max), or null to allocate it.
template <class T>
void pfn_forward_train(const Tensor<T>& input, const Tensor<T>& weight, const Tensor<T>& gamma,
                       const Tensor<T>& beta, const BatchNormOptions& options,
                       Tensor<T>& running_mean, Tensor<T>& running_var,
                       int64_t& num_batches_tracked, Tensor<T>& out, PfnSaved<T>& saved,
                       T* scratch = nullptr);

// Evaluation forward with the running statistics. Shapes as pfn_forward_train.
template <class T>
void pfn_forward_eval(const Tensor<T>& input, const Tensor<T>& weight, const Tensor<T>& gamma,
                      const Tensor<T>& beta, const Tensor<T>& running_mean,
                      const Tensor<T>& running_var, const BatchNormOptions& options,
                      Tensor<T>& out);

// Backward of the training forward. d_out (P, C); input, weight, gamma and saved as given to and
// written by the forward. Writes d_input (P, N, D), d_weight (C, D), d_gamma and d_beta (C).
// scratch: room for 2 P * N * C values (the recomputed linear output and its gradient), or null
// to allocate them.
template <class T>
void pfn_backward(const Tensor<T>& d_out, const Tensor<T>& input, const Tensor<T>& weight,
                  const Tensor<T>& gamma, const PfnSaved<T>& saved, Tensor<T>& d_input,
                  Tensor<T>& d_weight, Tensor<T>& d_gamma, Tensor<T>& d_beta, T* scratch = nullptr,
                  ReplicaSum* replicas = nullptr);

}  // namespace pillarseg::host
