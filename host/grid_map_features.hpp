// The six hand-crafted grid-map layers of Bieder et al. 2020 (the paper's baseline row), per
// cell of the (H, W) grid: log(1 + detections), log(1 + transmissions) (ray counts of the 2D
// observability walk), mean reflectance, min z and max z of the points inside the grid volume,
// and detections / (detections + transmissions). Cells without points have 0 reflectance and
// heights; cells no ray touched have ratio 0. Output (6, H, W) float.
#pragma once

#include <span>
#include <vector>

#include "core/grid.hpp"
#include "core/point.hpp"
#include "core/tensor.hpp"

namespace pillarseg::host {

inline constexpr int kGridMapLayers = 6;

Tensor<float> grid_map_features(std::span<const Point> points, const Tensor<uint32_t>& detections,
                                const Tensor<uint32_t>& transmissions, const GridSpec& grid);

}  // namespace pillarseg::host
