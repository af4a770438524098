#include "host/mask_unobserved.hpp"

#include "core/error.hpp"

namespace pillarseg::host {

void mask_unobserved(const Tensor<uint32_t>& transmissions, const Tensor<uint32_t>& detections,
                     Tensor<uint8_t>& labels, Tensor<float>* probabilities) {
  const int64_t cells = transmissions.numel();
  PS_CHECK(transmissions.rank() == 2 && detections.shape() == transmissions.shape() &&
               labels.numel() == cells,
           "mask_unobserved: expected ray counts (H, W) and labels of H * W values, given {}, {} "
           "and {}",
           shape_str(transmissions.shape()), shape_str(detections.shape()),
           shape_str(labels.shape()));
  PS_CHECK(probabilities == nullptr || (cells > 0 && probabilities->numel() % cells == 0) ||
               (cells == 0 && probabilities->numel() == 0),
           "mask_unobserved: probabilities {} are not whole class planes of H * W = {} cells",
           probabilities ? shape_str(probabilities->shape()) : std::string(), cells);
  const int64_t planes = probabilities && cells > 0 ? probabilities->numel() / cells : 0;
  for (int64_t c = 0; c < cells; ++c) {
    if (transmissions[c] + detections[c] != 0) continue;
    labels[c] = 0;
    for (int64_t k = 0; k < planes; ++k) (*probabilities)[k * cells + c] = 0.0f;
  }
}

}  // namespace pillarseg::host
