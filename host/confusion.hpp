// Confusion matrix over the 12 classes: rows are the true class, columns the predicted
// class (ids 1..12 stored at index id-1). Cells whose true label is 0 (unlabeled) are
// skipped, and so are cells where a mask (observability) is 0.
#pragma once

#include <cstdint>

#include "core/tensor.hpp"

namespace pillarseg::host {

// truth, predicted: (B, H, W) or (H, W) class ids 0..12; mask: same shape or nullptr.
// Adds into confusion (12, 12) int64.
void confusion_accumulate(const Tensor<uint8_t>& truth, const Tensor<uint8_t>& predicted, const Tensor<uint8_t>* mask,
                          Tensor<int64_t>& confusion);

}  // namespace pillarseg::host
