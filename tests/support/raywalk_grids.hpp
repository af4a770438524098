// The small grids of the ray-walk tests (tests/test_raywalk.cpp on the host, and
// tests/test_kernels_pipeline.cpp on the kernels), so that both walk the same cells.
#pragma once

#include "engine/core/grid.hpp"

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

}  // namespace pillarseg::test
