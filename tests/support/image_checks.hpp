// Pixel checks shared by the tests of rendered images (charts, figures): white pixels and the
// count of dark ones (text or lines) in a box.
#pragma once

#include <cstdint>

#include "engine/util/image.hpp"

namespace pillarseg::test {

inline bool is_white(const ImageRgb& image, int x, int y) {
  const uint8_t* p = image.at(x, y);
  return p[0] == 255 && p[1] == 255 && p[2] == 255;
}

// Pixels of the box [x0, x1) x [y0, y1) darker than light grey: text or lines.
inline int64_t count_dark(const ImageRgb& image, int x0, int y0, int x1, int y1) {
  int64_t n = 0;
  for (int y = y0; y < y1; ++y)
    for (int x = x0; x < x1; ++x) {
      const uint8_t* p = image.at(x, y);
      n += p[0] + p[1] + p[2] < 3 * 128;
    }
  return n;
}

}  // namespace pillarseg::test
