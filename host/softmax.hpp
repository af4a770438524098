// Per-cell softmax over the class channels and the predicted class map:
//   logits (B, K, H, W) -> probabilities (B, K, H, W), summing to 1 over K in each cell;
//   logits (B, K, H, W) -> class ids (B, H, W) uint8, id = 1 + arg-max channel (channel k holds
//   class k + 1; class 0, unlabeled, is never predicted);
//   values (B, K, H, W) -> class ids (B, H, W) of the largest positive value, 0 where none is.
#pragma once

#include <cstdint>

#include "core/tensor.hpp"

namespace pillarseg::host {

// logits (B, K, H, W) -> probabilities (B, K, H, W). Stable (the cell's max logit is subtracted
// first); a NaN logit makes the whole cell NaN, as do +inf logits (inf - inf), as in PyTorch.
template <class T>
void softmax_channels(const Tensor<T>& logits, Tensor<T>& probabilities);

// logits (B, K, H, W), K <= 255 -> class_ids (B, H, W) = 1 + the channel of the largest logit;
// ties go to the lower channel and a NaN counts as the largest, as torch.argmax.
template <class T>
void argmax_class_ids(const Tensor<T>& logits, Tensor<uint8_t>& class_ids);

// values (B, K, H, W), K <= 255 -> class_ids (B, H, W) = 1 + the channel of the largest positive
// value, ties to the lower channel; 0 where no value is positive (NaN never wins). For sums of
// probabilities (test-time flips): a cell masked as unobserved in every copy sums to 0 and keeps
// class 0, as mask_unobserved gives it in one pass.
template <class T>
void argmax_positive_class_ids(const Tensor<T>& values, Tensor<uint8_t>& class_ids);

}  // namespace pillarseg::host
