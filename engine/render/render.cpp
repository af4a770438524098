#include "engine/render/render.hpp"

#include <algorithm>
#include <cmath>

#include "core/error.hpp"

namespace pillarseg {

ImageRgb render_points(const std::vector<Point>& points, const std::vector<uint32_t>& labels, const ClassTable& classes,
                       const GridSpec& grid) {
  const int W = grid.width(), H = grid.height();
  ImageRgb img(W, H);
  const bool labelled = labels.size() == points.size() && !labels.empty();
  for (size_t i = 0; i < points.size(); ++i) {
    const Point& p = points[i];
    if (!grid.contains(p.x, p.y, p.z)) continue;
    const int x = static_cast<int>(grid.ix(p.x)), y = H - 1 - static_cast<int>(grid.iy(p.y));
    uint8_t* px = img.at(x, y);
    if (labelled) {
      const Rgb c = classes.color(classes.class_of(labels[i]));
      // Unlabelled points stay visible in dark grey.
      const bool unlabeled = classes.class_of(labels[i]) == 0;
      px[0] = unlabeled ? 90 : c.r, px[1] = unlabeled ? 90 : c.g, px[2] = unlabeled ? 90 : c.b;
    } else {
      const double t = (p.z - grid.z_min) / (grid.z_max - grid.z_min);
      const auto v = static_cast<uint8_t>(std::clamp(80.0 + 175.0 * t, 0.0, 255.0));
      px[0] = px[1] = px[2] = std::max(px[0], v);
    }
  }
  return img;
}

ImageRgb render_observability(const Tensor<uint32_t>& counts) {
  PS_CHECK(counts.rank() == 2, "render_observability: expected (H, W), got {}", shape_str(counts.shape()));
  const int H = static_cast<int>(counts.dim(0)), W = static_cast<int>(counts.dim(1));
  uint32_t max_count = 1;
  for (uint32_t c : counts) max_count = std::max(max_count, c);
  const double scale = 255.0 / std::log1p(static_cast<double>(max_count));
  ImageRgb img(W, H);
  for (int iy = 0; iy < H; ++iy)
    for (int ix = 0; ix < W; ++ix) {
      const auto v = static_cast<uint8_t>(std::lround(std::log1p(static_cast<double>(counts(iy, ix))) * scale));
      uint8_t* px = img.at(ix, H - 1 - iy);
      px[0] = px[1] = px[2] = v;
    }
  return img;
}

ImageRgb render_occupancy(const Tensor<float>& p) {
  PS_CHECK(p.rank() == 3, "render_occupancy: expected (Z, H, W), got {}", shape_str(p.shape()));
  const int Z = static_cast<int>(p.dim(0)), H = static_cast<int>(p.dim(1)), W = static_cast<int>(p.dim(2));
  ImageRgb img(W, H);
  for (int iy = 0; iy < H; ++iy)
    for (int ix = 0; ix < W; ++ix) {
      // Red: the most occupied layer above 0.5; green: the most free layer below it.
      float occupied = 0, free_ = 0;
      for (int z = 0; z < Z; ++z) {
        const float v = p(z, iy, ix);
        occupied = std::max(occupied, v - 0.5f);
        free_ = std::max(free_, 0.5f - v);
      }
      uint8_t* px = img.at(ix, H - 1 - iy);
      px[0] = static_cast<uint8_t>(std::lround(510.0f * occupied));
      px[1] = static_cast<uint8_t>(std::lround(510.0f * free_));
      px[2] = 0;
    }
  return img;
}

void apply_mask(ImageRgb& image, const Tensor<uint8_t>& mask) {
  PS_CHECK(mask.rank() == 2 && mask.dim(0) == image.height && mask.dim(1) == image.width,
           "apply_mask: mask {} does not match the {}x{} image", shape_str(mask.shape()), image.width, image.height);
  for (int iy = 0; iy < image.height; ++iy)
    for (int ix = 0; ix < image.width; ++ix)
      if (!mask(iy, ix)) {
        uint8_t* px = image.at(ix, image.height - 1 - iy);
        px[0] = px[1] = px[2] = 0;
      }
}

}  // namespace pillarseg
