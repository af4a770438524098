// The small grids (and the near-tie rays) of the ray-walk tests (tests/test_raywalk.cpp on the
// host, and tests/test_kernels_pipeline.cpp on the kernels), so that both walk the same cells.
#pragma once

#include <cmath>
#include <cstdlib>
#include <vector>

#include "core/grid.hpp"
#include "core/point.hpp"

namespace pillarseg::test {

// 3.3 m x 2.1 m x 1 m at 0.1 m cells and 0.2 m voxels: W = 33, H = 21, Z = 5 (odd sizes).
inline GridSpec small_grid() {
  GridSpec grid;
  grid.x_min = -1.3;
  grid.x_max = 2.0;
  grid.y_min = -0.9;
  grid.y_max = 1.2;
  grid.z_min = -0.5;
  grid.z_max = 0.5;
  return grid;
}

// Cell 0.25 m and voxel 0.5 m, so that points on a 1/8 m lattice have exact cell coordinates
// and rays through cell corners, edges and borders are common: W = 19, H = 11, Z = 3.
inline GridSpec dyadic_grid() {
  GridSpec grid;
  grid.x_min = -2.0;
  grid.x_max = 2.75;
  grid.y_min = -1.5;
  grid.y_max = 1.25;
  grid.z_min = -1.0;
  grid.z_max = 0.5;
  grid.cell = 0.25;
  grid.voxel_z = 0.5;
  return grid;
}

// A 10 m x 10 m grid of 0.1 m cells around the origin (0, 0, 0), and rays from it through points
// twice as far as the float nearest to a cell corner near the sensor (|x|, |y| <= 0.3 m), give or
// take a few float ulps: each ray passes within about 1e-7 cells of that corner, inside the walk's
// tie window (2^-30 (W + 2 + |u_origin|) cells), but rarely exactly through it, so the crossings
// are decided by the exact orientation sign, positive or negative.
inline GridSpec near_tie_grid() {
  GridSpec grid;
  grid.x_min = -5.0;
  grid.x_max = 5.0;
  grid.y_min = -5.0;
  grid.y_max = 5.0;
  grid.z_min = -1.0;
  grid.z_max = 1.0;
  return grid;
}

inline std::vector<Point> near_tie_rays() {
  std::vector<Point> points;
  for (int i = -3; i <= 3; ++i)
    for (int j = -3; j <= 3; ++j)
      for (int jitter_x = -2; jitter_x <= 2; ++jitter_x)
        for (int jitter_y = -2; jitter_y <= 2; ++jitter_y) {
          float x = 2.0f * static_cast<float>(0.1 * i), y = 2.0f * static_cast<float>(0.1 * j);
          for (int k = 0; k < std::abs(jitter_x); ++k) x = std::nextafter(x, jitter_x * 1.0f);
          for (int k = 0; k < std::abs(jitter_y); ++k) y = std::nextafter(y, jitter_y * 1.0f);
          points.push_back(Point{x, y, 0.3f * static_cast<float>(i - j), 0.0f});
        }
  return points;
}

}  // namespace pillarseg::test
