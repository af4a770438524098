#include "host/observability_input.hpp"

#include <cmath>

#include "core/error.hpp"

namespace pillarseg::host {

void observability_input(const Tensor<uint32_t>& transmissions, const Tensor<uint32_t>& detections,
                         Tensor<float>& out) {
  PS_CHECK(transmissions.rank() == 2 && detections.shape() == transmissions.shape(),
           "observability_input: expected transmissions and detections of one shape (H, W), given "
           "{} and {}",
           shape_str(transmissions.shape()), shape_str(detections.shape()));
  PS_CHECK(out.numel() == transmissions.numel(),
           "observability_input: the output must hold H * W = {} values, given {}",
           transmissions.numel(), shape_str(out.shape()));
  for (int64_t i = 0; i < out.numel(); ++i) {
    const uint32_t rays = transmissions[i] + detections[i];
    out[i] = static_cast<float>(std::log1p(static_cast<double>(rays)));
  }
}

}  // namespace pillarseg::host
