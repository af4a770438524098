// Segmentation losses over the labelled cells of a batch, with their gradients:
//   logits (B, K, H, W), channel k scoring class k + 1 (K = 12);
//   labels (B, H, W) uint8 in 0..K, 0 = unlabeled (ignored: no loss, zero gradient);
//   class_weights (K + 1) indexed by class id (entry 0 unused), all >= 0.
// M is the number of labelled cells; with M = 0 the loss and its gradient are 0.
// Losses are accumulated in double and returned as double; d_logits (B, K, H, W) is the gradient
// of the returned loss, written when the pointer is not null (nullptr: loss only).
#pragma once

#include <cstdint>
#include <span>
#include <type_traits>

#include "core/lovasz.hpp"
#include "core/tensor.hpp"

namespace pillarseg::host {

// Weighted softmax cross-entropy (the default loss):
//   L = -(1 / M) * sum over labelled cells i of c[y_i] * log softmax(z_i)[y_i - 1].
// Computed as c[y] * (logsumexp(z) - z[y - 1]), stable for large logits.
template <class T>
double cross_entropy_loss(const Tensor<T>& logits, const Tensor<uint8_t>& labels,
                          std::span<const double> class_weights,
                          std::type_identity_t<Tensor<T>>* d_logits);

// Sigmoid binary cross-entropy on one-hot targets (the authors' `bce` loss), channel k weighted
// by c[k + 1], mean over the M * K (cell, channel) pairs of labelled cells, as PyTorch's
// F.binary_cross_entropy_with_logits(z, onehot, weight=c[1:], reduction='mean'):
//   L = (1 / (M K)) * sum over labelled i, k of c[k + 1] * (t ? softplus(-z) : softplus(z)),
// with t = (y_i == k + 1) and softplus(x) = log(1 + exp(x)) computed stably.
template <class T>
double bce_loss(const Tensor<T>& logits, const Tensor<uint8_t>& labels,
                std::span<const double> class_weights, std::type_identity_t<Tensor<T>>* d_logits);

// Lovász-softmax (Berman, Rannen Triki and Blaschko, CVPR 2018), the convex surrogate of the
// Jaccard loss that SalsaNext and Cylinder3D add to the cross-entropy: for each class c present in
// the labels, the errors e_i = |[y_i == c] - softmax(z_i)[c - 1]| of the M labelled cells, taken
// from the largest down, weigh the steps of the Jaccard loss 1 - |fg \ first j| / |fg u first j|;
// the loss is the mean over the present classes, in [0, 1]. The errors are ranked by 4096 bins
// of [0, 1] (core/lovasz.hpp) rather than sorted: the cells of one bin share its Jaccard step equally (the step over
// a bin does not depend on the order inside it), so the result is the sorted loss wherever no two
// cells of one bin differ, within 1 / 4096 of it otherwise, and needs no sort on a device. Its
// gradient, as the paper's, holds the ranking fixed. Class weights are not used: the loss already
// weighs each class's IoU alike.
template <class T>
double lovasz_softmax_loss(const Tensor<T>& logits, const Tensor<uint8_t>& labels,
                           std::type_identity_t<Tensor<T>>* d_logits);

}  // namespace pillarseg::host
