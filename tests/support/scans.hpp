// Synthetic scans for the pipeline tests: crowded cells, border points, points outside the grid
// and non-finite ones, deterministic by seed.
#pragma once

#include <cstdint>
#include <limits>
#include <vector>

#include "core/grid.hpp"
#include "core/point.hpp"
#include "core/rng.hpp"

namespace pillarseg::test {

// A scan for `grid`: most points in a few crowded cells (pillars of more than N points), the rest
// spread over and beyond the grid (x, y or z outside), on cell borders, and some non-finite.
inline std::vector<Point> random_scan(std::int64_t count, const GridSpec& grid, std::uint64_t seed) {
  Rng rng(seed);
  std::vector<Point> points(static_cast<std::size_t>(count));
  const double margin = 4 * grid.cell;
  for (Point& p : points) {
    const std::uint64_t kind = rng.uniform_int(10);
    if (kind < 4) {  // one of 5 crowded cells
      const auto c = static_cast<double>(rng.uniform_int(5));
      p.x = static_cast<float>(grid.x_min + (3 * c + 1.5) * grid.cell +
                               rng.uniform(-0.4, 0.4) * grid.cell);
      p.y = static_cast<float>(grid.y_min + (c + 2.5) * grid.cell);
    } else if (kind < 5) {  // on a cell border
      p.x = static_cast<float>(
          grid.x_min + grid.cell * static_cast<double>(
                                       rng.uniform_int(static_cast<std::uint64_t>(grid.width()))));
      p.y = static_cast<float>(grid.y_min + rng.uniform(0.0, grid.y_max - grid.y_min));
    } else {
      p.x = static_cast<float>(rng.uniform(grid.x_min - margin, grid.x_max + margin));
      p.y = static_cast<float>(rng.uniform(grid.y_min - margin, grid.y_max + margin));
    }
    p.z = static_cast<float>(rng.uniform(grid.z_min - 0.2, grid.z_max + 0.2));
    p.r = static_cast<float>(rng.uniform(0.0, 1.0));
    if (kind == 9 && rng.uniform_int(4) == 0) p.z = rng.uniform_int(2) == 0 ? std::numeric_limits<float>::quiet_NaN() : std::numeric_limits<float>::infinity();
  }
  return points;
}

}  // namespace pillarseg::test
