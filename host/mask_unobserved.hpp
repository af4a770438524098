// Masking of unobserved cells (the paper's filtered predictions, --mask-unobserved): a cell that
// no ray touched (transmissions + detections = 0) gets class 0 (unlabeled) and, in every class
// plane of the probabilities, 0.
#pragma once

#include <cstdint>

#include "core/tensor.hpp"

namespace pillarseg::host {

// transmissions, detections (H, W); labels (H W values); probabilities (K H W values) or null.
void mask_unobserved(const Tensor<uint32_t>& transmissions, const Tensor<uint32_t>& detections,
                     Tensor<uint8_t>& labels, Tensor<float>* probabilities);

}  // namespace pillarseg::host
