// Sparse ground-truth rule (DESIGN.md section 1 "Ground truth"): rasterises labelled points
// into a top-view class map. Per cell of the (H, W) grid, n_k counts the points of class k
// inside the grid volume (GridSpec::contains: x, y and z); the cell's class is
// argmax_k w_k * n_k over k = 1..12 with w_k = ClassTable::gt_weight(k), ties going to the
// lower class id. A cell without a point of positive weight is 0 (unlabeled).
// Output: Tensor<uint8_t> (H, W), row iy, column ix.
#pragma once

#include <cstdint>
#include <span>

#include "core/classes.hpp"
#include "core/grid.hpp"
#include "core/point.hpp"
#include "core/tensor.hpp"

namespace pillarseg {

// points (N), class_ids (N) in 0..12 (already mapped, e.g. an aggregated point set).
// Returns (H, W).
Tensor<uint8_t> rasterize_classes(std::span<const Point> points, std::span<const uint8_t> class_ids,
                                  const ClassTable& table, const GridSpec& grid);

// points (N), raw_labels (N) raw .label words, mapped with ClassTable::class_of.
// Returns (H, W).
Tensor<uint8_t> rasterize_labels(std::span<const Point> points,
                                 std::span<const uint32_t> raw_labels, const ClassTable& table,
                                 const GridSpec& grid);

}  // namespace pillarseg
