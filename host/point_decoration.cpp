// Point decoration: (M points, P' pillars of N slots) -> (P', N, 10) features (see
// point_decoration.hpp). Pillars are independent: each thread writes the rows of its own
// contiguous range of pillars (kept points, then zero padding), so the result does not depend on
// the thread count.
#include "host/point_decoration.hpp"

#include <algorithm>

#include "engine/core/error.hpp"
#include "engine/core/parallel.hpp"

namespace pillarseg::host {

namespace {

// Shapes (P', 2), (P', N), (P'); counts in [0, N]; kept indices inside the scan; cells inside
// the grid. Checked before the parallel loop so that no exception leaves a worker thread.
void check_pillars(const std::vector<Point>& points, const Pillars& pillars, const GridSpec& grid) {
  const Tensor<int32_t>& counts = pillars.count;
  PS_CHECK(counts.rank() == 1, "decorate_points: pillar count must be (P'), given {}",
           shape_str(counts.shape()));
  const int64_t num_pillars = counts.dim(0);
  PS_CHECK(pillars.cell.shape() == Shape({num_pillars, 2}),
           "decorate_points: pillar cell must be ({}, 2), given {}", num_pillars,
           shape_str(pillars.cell.shape()));
  PS_CHECK(pillars.point_index.rank() == 2 && pillars.point_index.dim(0) == num_pillars &&
               pillars.point_index.dim(1) >= 1,
           "decorate_points: point_index must be ({}, N) with N >= 1, given {}", num_pillars,
           shape_str(pillars.point_index.shape()));
  const int64_t slots = pillars.point_index.dim(1);
  const int64_t num_points = static_cast<int64_t>(points.size());
  const int64_t width = grid.width(), height = grid.height();
  for (int64_t p = 0; p < num_pillars; ++p) {
    const int32_t count = counts[p];
    PS_CHECK(count >= 0 && count <= slots,
             "decorate_points: pillar {} has count {}, expected 0..{}", p, count, slots);
    for (int32_t k = 0; k < count; ++k) {
      const int32_t index = pillars.point_index(p, k);
      PS_CHECK(index >= 0 && index < num_points,
               "decorate_points: pillar {} slot {} points at {}, expected 0..{} (scan size)", p, k,
               index, num_points - 1);
    }
    const int32_t iy = pillars.cell(p, 0), ix = pillars.cell(p, 1);
    PS_CHECK(iy >= 0 && iy < height && ix >= 0 && ix < width,
             "decorate_points: pillar {} has cell (iy {}, ix {}) outside the {} x {} grid", p, iy,
             ix, height, width);
  }
}

}  // namespace

void decorate_points(const std::vector<Point>& points, const Pillars& pillars, const GridSpec& grid,
                     Tensor<float>& out) {
  check_pillars(points, pillars, grid);
  const int64_t num_pillars = pillars.num_pillars();
  const int64_t slots = pillars.point_index.dim(1);
  // Keep the capacity of `out`: every element is written below.
  out.resize_for_overwrite({num_pillars, slots, kDecoratedFeatures});

  const double centre_z = grid.z_min + 0.5 * (grid.z_max - grid.z_min);
  parallel_chunks(num_pillars, [&](int64_t begin, int64_t end, int) {
    for (int64_t p = begin; p < end; ++p) {
      const int32_t* index = &pillars.point_index(p, 0);
      const int32_t count = pillars.count[p];
      const double centre_x = grid.x_min + (pillars.cell(p, 1) + 0.5) * grid.cell;
      const double centre_y = grid.y_min + (pillars.cell(p, 0) + 0.5) * grid.cell;
      // One gather of the points: the features that need no mean, and the sums; then the
      // offsets from the mean, from the copies of x, y, z in the rows (floats, so exact).
      float* rows = &out(p, 0, 0);
      float* row = rows;
      double sum_x = 0, sum_y = 0, sum_z = 0;
      for (int32_t k = 0; k < count; ++k, row += kDecoratedFeatures) {
        const Point& pt = points[static_cast<size_t>(index[k])];
        const double x = pt.x, y = pt.y, z = pt.z;
        sum_x += x, sum_y += y, sum_z += z;
        row[0] = pt.x;
        row[1] = pt.y;
        row[2] = pt.z;
        row[3] = pt.r;
        row[7] = static_cast<float>(x - centre_x);
        row[8] = static_cast<float>(y - centre_y);
        row[9] = static_cast<float>(z - centre_z);
      }
      const double mean_x = count > 0 ? sum_x / count : 0.0;
      const double mean_y = count > 0 ? sum_y / count : 0.0;
      const double mean_z = count > 0 ? sum_z / count : 0.0;
      for (float* r = rows; r < row; r += kDecoratedFeatures) {
        r[4] = static_cast<float>(r[0] - mean_x);
        r[5] = static_cast<float>(r[1] - mean_y);
        r[6] = static_cast<float>(r[2] - mean_z);
      }
      // Padding rows right after the kept ones, so that each line of the output is written
      // once, while it is in cache.
      std::fill(row, row + (slots - count) * kDecoratedFeatures, 0.0f);
    }
  });
}

Tensor<float> decorate_points(const std::vector<Point>& points, const Pillars& pillars,
                              const GridSpec& grid) {
  Tensor<float> out;
  decorate_points(points, pillars, grid, out);
  return out;
}

}  // namespace pillarseg::host
