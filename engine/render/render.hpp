// Top-view pictures, all W wide and H high with +x to the right and +y up (image row
// H-1-iy), like the paper's Fig. 3: the points (class colours, or grey by height without
// labels), the observability map (log scale), the occupancy map, and label maps
// (engine/render/label_map.hpp); engine/render/figure.hpp lays panels out with titles, a class
// legend and a scale bar.
#pragma once

#include <vector>

#include "core/classes.hpp"
#include "core/grid.hpp"
#include "core/point.hpp"
#include "core/tensor.hpp"
#include "engine/util/image.hpp"

namespace pillarseg {

ImageRgb render_points(const std::vector<Point>& points, const std::vector<uint32_t>& labels, const ClassTable& classes,
                       const GridSpec& grid);
ImageRgb render_observability(const Tensor<uint32_t>& counts);  // (H, W)
ImageRgb render_occupancy(const Tensor<float>& probability);     // (Z, H, W)
// Cells where mask is 0 are drawn black (the paper's filtered predictions).
void apply_mask(ImageRgb& image, const Tensor<uint8_t>& mask);

}  // namespace pillarseg
