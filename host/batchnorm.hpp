// BatchNorm over channel axis 1, PyTorch semantics (torch.nn.BatchNorm1d/2d), optionally fused
// with the ReLU that follows it. x is (B, C, H, W) (U-Net, occupancy stream) or (M, C) (the PFN's
// M = P * N linear outputs); gamma, beta, running_mean, running_var and the saved statistics
// are (C).
//   training: y = gamma * (x - mean) / sqrt(var + eps) + beta with the batch mean and the biased
//             batch variance over all values of a channel; running_mean and running_var move
//             towards the batch mean and the *unbiased* batch variance by `momentum`, and
//             num_batches_tracked counts the call.
//   evaluation: the same with running_mean and running_var in place of the batch statistics.
// Statistics are accumulated in double for both element types.
#pragma once

#include <cstdint>

#include "core/replicas.hpp"
#include "core/tensor.hpp"

namespace pillarseg::host {

// PyTorch's eps and momentum: U-Net 1e-5 / 0.1 (the defaults), PFN and occupancy stream
// 1e-3 / 0.01.
struct BatchNormOptions {
  double eps = 1e-5;
  double momentum = 0.1;
  // Synchronised BatchNorm in a data-parallel run: the statistics (and, in the backward, the
  // sums dx needs) are those of the values of all replicas; nullptr: this process's values.
  ReplicaSum* replicas = nullptr;
};

// What the training forward keeps for the backward.
template <class T>
struct BatchNormSaved {
  Tensor<T> mean;     // (C) batch mean
  Tensor<T> inv_std;  // (C) 1 / sqrt(biased batch variance + eps)
};

// Training forward. x (B, C, H, W) or (M, C); gamma, beta (C); running_mean, running_var (C)
// updated in place, num_batches_tracked incremented. Writes y (shape of x; y may be x, in place)
// and saved (C).
// A channel needs more than one value (as PyTorch; the unbiased variance is undefined
// otherwise). An empty x (B = 0 or M = 0, e.g. a PFN over no pillars) gives an empty y and
// leaves the running statistics as they are, while num_batches_tracked still counts the call,
// as torch.nn.BatchNorm does for an empty batch.
template <class T>
void batchnorm_forward_train(const Tensor<T>& x, const Tensor<T>& gamma, const Tensor<T>& beta,
                             const BatchNormOptions& options, Tensor<T>& running_mean,
                             Tensor<T>& running_var, int64_t& num_batches_tracked, Tensor<T>& y,
                             BatchNormSaved<T>& saved);

// Evaluation forward with the running statistics. Shapes as batchnorm_forward_train; y may be
// x (in place).
template <class T>
void batchnorm_forward_eval(const Tensor<T>& x, const Tensor<T>& gamma, const Tensor<T>& beta,
                            const Tensor<T>& running_mean, const Tensor<T>& running_var,
                            const BatchNormOptions& options, Tensor<T>& y);

// Backward of the training forward. dy, x (B, C, H, W) or (M, C); gamma (C); saved from the
// forward. Writes dx (shape of x; dx may be dy, in place), dgamma and dbeta (C). With replicas
// (the forward's), dx is the gradient through the statistics of all replicas' values, while
// dgamma and dbeta are this replica's share of the parameters' gradient.
template <class T>
void batchnorm_backward(const Tensor<T>& dy, const Tensor<T>& x, const Tensor<T>& gamma,
                        const BatchNormSaved<T>& saved, Tensor<T>& dx, Tensor<T>& dgamma,
                        Tensor<T>& dbeta, ReplicaSum* replicas = nullptr);

// Fused BatchNorm + ReLU: y = max(batchnorm(x), 0), NaN passing through. Same arguments as the
// plain versions; the backward also takes the forward's output y, whose zeros block dy.
template <class T>
void batchnorm_relu_forward_train(const Tensor<T>& x, const Tensor<T>& gamma, const Tensor<T>& beta,
                                  const BatchNormOptions& options, Tensor<T>& running_mean,
                                  Tensor<T>& running_var, int64_t& num_batches_tracked,
                                  Tensor<T>& y, BatchNormSaved<T>& saved);

template <class T>
void batchnorm_relu_forward_eval(const Tensor<T>& x, const Tensor<T>& gamma, const Tensor<T>& beta,
                                 const Tensor<T>& running_mean, const Tensor<T>& running_var,
                                 const BatchNormOptions& options, Tensor<T>& y);

template <class T>
void batchnorm_relu_backward(const Tensor<T>& dy, const Tensor<T>& x, const Tensor<T>& y,
                             const Tensor<T>& gamma, const BatchNormSaved<T>& saved, Tensor<T>& dx,
                             Tensor<T>& dgamma, Tensor<T>& dbeta, ReplicaSum* replicas = nullptr);

}  // namespace pillarseg::host
