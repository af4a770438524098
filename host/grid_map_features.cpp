#include "host/grid_map_features.hpp"

#include <cmath>
#include <limits>

#include "core/error.hpp"

namespace pillarseg::host {

Tensor<float> grid_map_features(std::span<const Point> points, const Tensor<uint32_t>& detections,
                                const Tensor<uint32_t>& transmissions, const GridSpec& grid) {
  const int64_t H = grid.height(), W = grid.width(), cells = H * W;
  PS_CHECK(detections.shape() == (Shape{H, W}) && transmissions.shape() == (Shape{H, W}),
           "grid_map_features: ray counts must be ({}, {}), got {} and {}", H, W, shape_str(detections.shape()),
           shape_str(transmissions.shape()));
  Tensor<float> out({kGridMapLayers, H, W});
  std::vector<double> reflectance(static_cast<size_t>(cells), 0.0);
  std::vector<int32_t> count(static_cast<size_t>(cells), 0);
  std::vector<float> zmin(static_cast<size_t>(cells), std::numeric_limits<float>::infinity());
  std::vector<float> zmax(static_cast<size_t>(cells), -std::numeric_limits<float>::infinity());
  for (const Point& p : points) {
    if (!grid.contains(p.x, p.y, p.z) || !(std::fabs(p.r) <= kMaxAbsReflectance)) continue;  // as pillar_gather
    const size_t c = static_cast<size_t>(grid.cell_index(p.x, p.y));
    reflectance[c] += p.r;
    count[c] += 1;
    zmin[c] = std::min(zmin[c], p.z);
    zmax[c] = std::max(zmax[c], p.z);
  }
  float* layer = out.data();
  for (int64_t c = 0; c < cells; ++c) {
    const double det = detections[c], trans = transmissions[c];
    const size_t i = static_cast<size_t>(c);
    layer[0 * cells + c] = static_cast<float>(std::log1p(det));
    layer[1 * cells + c] = static_cast<float>(std::log1p(trans));
    layer[2 * cells + c] = count[i] ? static_cast<float>(reflectance[i] / count[i]) : 0.0f;
    layer[3 * cells + c] = count[i] ? zmin[i] : 0.0f;
    layer[4 * cells + c] = count[i] ? zmax[i] : 0.0f;
    layer[5 * cells + c] = det + trans > 0 ? static_cast<float>(det / (det + trans)) : 0.0f;
  }
  return out;
}

}  // namespace pillarseg::host
