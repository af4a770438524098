// Segmentation losses over the labelled cells of a batch, with their gradients (host/losses.hpp
// is the spec):
//   logits (B, K, H, W) seen as (B, K, S), S = H * W, channel k scoring class k + 1 (K = 12);
//   labels (B, S) uint8 in 0..K, 0 = unlabeled (no loss, zero gradient);
//   class_weights (K + 1) floats indexed by class id (entry 0 unused), finite and >= 0.
//   cross_entropy_loss: L = (1 / M) sum over labelled cells of c[y] (logsumexp(z) - z[y - 1]);
//   bce_loss:           L = (1 / (M K)) sum over labelled cells and channels k of
//                       c[k + 1] (t ? softplus(-z) : softplus(z)), t = (y == k + 1);
// M = the number of labelled cells (M = 0: loss and gradient 0). d_logits (B, K, S) is the
// gradient of L (nullptr: loss only).
// Three passes, none waiting for the host: per-block sums of the loss (in double) and of the
// label counts, one block adding them in a fixed order into a LossResult in device memory (the
// loss is deterministic), then the gradient, scaled by the 1 / M found there. loss_value brings
// the result to the host: the one call that waits.
// Pointers are device memory; the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "core/lovasz.hpp"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// What a loss leaves in device memory.
struct LossResult {
  double loss = 0.0;
  double gradient_scale = 0.0;      // 1 / M (cross-entropy) or 1 / (M K) (bce), 0 when M = 0
  std::int64_t labelled = 0;        // M
  std::int64_t invalid_labels = 0;  // labels > K, treated as unlabeled
  std::int64_t classes = 0;         // K
};

// Per-block sums of the first pass.
struct LossPartial {
  double loss = 0.0;
  std::int64_t labelled = 0;
  std::int64_t invalid_labels = 0;
};

// The workspace of both losses: kLossPartials LossPartial.
inline constexpr int kLossPartials = 1024;

// logits (B, K, S), labels (B, S), class_weights (K + 1) -> *result, d_logits (B, K, S) or
// nullptr. d_logits does not overlap the logits.
void cross_entropy_loss(const float* logits, const std::uint8_t* labels, std::int64_t batch,
                        std::int64_t classes, std::int64_t inner, const float* class_weights,
                        float* d_logits, LossPartial* workspace, LossResult* result,
                        cudaStream_t stream);

void bce_loss(const float* logits, const std::uint8_t* labels, std::int64_t batch,
              std::int64_t classes, std::int64_t inner, const float* class_weights, float* d_logits,
              LossPartial* workspace, LossResult* result, cudaStream_t stream);

// Lovász-softmax (host/losses.hpp: lovasz_softmax_loss, the spec; errors ranked by
// kLovaszBins bins of [0, 1]), weighted by `weight` and ADDED to result->loss and to d_logits
// (which hold a loss already: the cross-entropy's), or only to the loss when d_logits is null.
//   [histogram] one thread per cell: its softmax, then per class the bin of its error, counted
//               (foreground, background) with integer atomics: the counts are exact;
//   [steps]     one block per class: descending prefix sums of the counts over the bins, each
//               bin's Jaccard step shared by its cells; the class's foreground total;
//   [cells]     one thread per cell: the loss terms (per-block sums in double) and the gradient;
//   [finalize]  one block adds the block sums in a fixed order into result->loss.
// counts: (K, kLovaszBins, 2) + K ints, steps: K * kLovaszBins doubles (lovasz_workspace_*).
constexpr std::int64_t lovasz_count_ints(std::int64_t classes) {
  return classes * kLovaszBins * 2 + classes;
}
constexpr std::int64_t lovasz_step_doubles(std::int64_t classes) { return classes * kLovaszBins; }

void lovasz_softmax_loss(const float* logits, const std::uint8_t* labels, std::int64_t batch,
                         std::int64_t classes, std::int64_t inner, float weight, float* d_logits,
                         int* counts, double* steps, LossPartial* workspace, LossResult* result,
                         cudaStream_t stream);

// Waits for `stream`, copies *result to the host and returns the loss. Throws pillarseg::Error
// when some labels were not class ids 0..K (their cells counted as unlabeled).
double loss_value(const LossResult* result, cudaStream_t stream);

}  // namespace pillarseg::cuda
