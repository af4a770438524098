// Point decoration (the input of OpenPCDet's PillarVFE, DESIGN.md section 1 "Pillars"): for P'
// pillars of N slots, a (P', N, D = 10) float tensor whose row for a kept point is
//   x, y, z, r,
//   x - mean_x, y - mean_y, z - mean_z   (mean of the pillar's kept points, in double),
//   x - cx, y - cy, z - cz               (pillar centre: cx = x_min + (ix + 0.5) * cell,
//                                         cy likewise, cz = middle of the z range),
// and padding slots (slot >= count) are all-zero rows.
#pragma once

#include <span>
#include <vector>

#include "core/grid.hpp"
#include "core/point.hpp"
#include "core/tensor.hpp"
#include "host/pillar_gather.hpp"

namespace pillarseg::host {

inline constexpr int kDecoratedFeatures = 10;  // D

// points: the M points the pillars index into; pillars: from pillar_gather on the same grid.
// Returns (P', N, 10). Pillars are independent, so they are split over num_threads() threads
// and the result is the same for any thread count.
Tensor<float> decorate_points(std::span<const Point> points, const Pillars& pillars,
                              const GridSpec& grid);

// Same, written into `out`, which is reshaped to (P', N, 10) and keeps its allocation when it
// already holds at least P' * N * 10 floats (no allocation in a steady-state inference loop).
// Both throw pillarseg::Error naming the first pillar with a count outside [0, N], a kept index
// outside the scan or a cell outside the grid; `out` then holds no result.
void decorate_points(std::span<const Point> points, const Pillars& pillars, const GridSpec& grid,
                     Tensor<float>& out);

}  // namespace pillarseg::host
