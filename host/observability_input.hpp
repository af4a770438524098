// The 2D occupancy input of the network (DESIGN.md section 2): per cell of the (H, W) grid,
// log(1 + n) of the n = transmissions + detections rays that touched it (the observability map,
// summed in uint32), evaluated in double and rounded to float once.
#pragma once

#include <cstdint>

#include "core/tensor.hpp"

namespace pillarseg::host {

// transmissions, detections (H, W) -> out (H * W values: (H, W) or (1, H, W)).
void observability_input(const Tensor<uint32_t>& transmissions, const Tensor<uint32_t>& detections,
                         Tensor<float>& out);

}  // namespace pillarseg::host
