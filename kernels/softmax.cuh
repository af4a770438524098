// Per-cell softmax over the class channels and the predicted class map (host/softmax.hpp is the
// spec), logits (B, K, H, W) seen as (B, K, S), S = H * W:
//   softmax_channels: -> probabilities (B, K, S), p_k = exp(z_k - max z) / sum_j exp(z_j - max z);
//                     a NaN logit, or a +Inf one (Inf - Inf), makes the whole cell NaN.
//   argmax_class_ids: -> class_ids (B, S) uint8 = 1 + the channel of the largest logit (channel
//                     k scores class k + 1); ties go to the lower channel, a NaN counts as the
//                     largest (the first NaN), as torch.argmax.
//   argmax_positive_class_ids: values (B, K, S) -> class_ids (B, S) uint8 = 1 + the channel of the
//                     largest positive value, ties to the lower channel; 0 where none is positive
//                     (NaN never wins): the test-time flips' sum of probabilities.
// One thread per cell; reads along a channel plane are coalesced. Pointers are device memory;
// the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// logits (batch, classes, inner) -> probabilities (same shape), classes >= 1. Not in place.
void softmax_channels(const float* logits, std::int64_t batch, std::int64_t classes,
                      std::int64_t inner, float* probabilities, cudaStream_t stream);

// logits (batch, classes, inner), 1 <= classes <= 255 -> class_ids (batch, inner).
void argmax_class_ids(const float* logits, std::int64_t batch, std::int64_t classes,
                      std::int64_t inner, std::uint8_t* class_ids, cudaStream_t stream);

// values (batch, classes, inner), 1 <= classes <= 255 -> class_ids (batch, inner).
void argmax_positive_class_ids(const float* values, std::int64_t batch, std::int64_t classes,
                               std::int64_t inner, std::uint8_t* class_ids, cudaStream_t stream);

}  // namespace pillarseg::cuda
