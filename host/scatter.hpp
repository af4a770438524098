// Pillar scatter (PointPillars PointPillarScatter) and its backward, the gather, and the cells it
// reads, made from the pillar gather's:
//   features (P, C), cells (P, 3) int32 rows (batch index, iy, ix) -> canvas (B, C, H, W),
//   canvas(b, c, iy, ix) = features(p, c) for the pillar p at (b, iy, ix), 0 where no pillar.
// The backward reads d_canvas (B, C, H, W) at the same cells into d_features (P, C).
// Cells must lie in the canvas and be unique within a batch item.
// batch_cells: the gather's cell (R, 2) rows (iy, ix) of one sample -> (R, 3) rows (sample, iy,
// ix), and (-1, -1, -1) for an unused row (cell (-1, -1)), which the CUDA scatter skips.
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

// cell (R, 2) int32 (iy, ix) -> cells (R, 3) int32 (sample, iy, ix); sample >= 0.
void batch_cells(const Tensor<int32_t>& cell, int sample, Tensor<int32_t>& cells);

}  // namespace pillarseg::host
