// Pillar scatter (PointPillars PointPillarScatter) and its backward, the gather:
//   features (P, C), cells (P, 3) int32 rows (batch index, iy, ix) -> canvas (B, C, H, W),
//   canvas(b, c, iy, ix) = features(p, c) for the pillar p at (b, iy, ix), 0 where no pillar.
// The backward reads d_canvas (B, C, H, W) at the same cells into d_features (P, C).
// Cells must lie in the canvas and be unique within a batch item.
#pragma once

#include <cstdint>

#include "core/tensor.hpp"

namespace pillarseg::host {

// features (P, C); cells (P, 3) int32 (b, iy, ix); writes canvas (batch_size, C, height, width).
template <class T>
void scatter_forward(const Tensor<T>& features, const Tensor<int32_t>& cells, int64_t batch_size,
                     int64_t height, int64_t width, Tensor<T>& canvas);

// d_canvas (B, C, H, W); cells (P, 3) int32 (b, iy, ix); writes d_features (P, C).
template <class T>
void scatter_backward(const Tensor<T>& d_canvas, const Tensor<int32_t>& cells,
                      Tensor<T>& d_features);

}  // namespace pillarseg::host
