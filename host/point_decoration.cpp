// Point decoration: (M points, P' pillars of N slots) -> (P', N, 10) features (see
// point_decoration.hpp). Pillars are independent: each thread writes the rows of its own
// contiguous range of pillars (kept points and zero padding), checking each pillar as it reads
// it, so the result does not depend on the thread count.
#include "host/point_decoration.hpp"

#include <algorithm>
#include <cstdint>
#include <vector>

#include "core/eigen.hpp"
#include "core/error.hpp"
#include "core/parallel.hpp"

namespace pillarseg::host {

namespace {

// Shapes (P', 2), (P', N), (P'). Checked before the parallel loop so that no exception leaves a
// worker thread.
void check_shapes(const Pillars& pillars) {
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
}

// Throws for the first pillar with a count outside [0, N], a kept index outside the scan or a
// cell outside the grid (decorate_range found one and skipped it).
void throw_first_fault(std::span<const Point> points, const Pillars& pillars,
                       const GridSpec& grid) {
  const int64_t slots = pillars.point_index.dim(1);
  const auto num_points = static_cast<int64_t>(points.size());
  const int64_t width = grid.width(), height = grid.height();
  for (int64_t p = 0; p < pillars.num_pillars(); ++p) {
    const int32_t kept = pillars.count[p];
    PS_CHECK(kept >= 0 && kept <= slots, "decorate_points: pillar {} has count {}, expected 0..{}",
             p, kept, slots);
    for (int32_t k = 0; k < kept; ++k) {
      const int32_t point = pillars.point_index(p, k);
      PS_CHECK(point >= 0 && point < num_points,
               "decorate_points: pillar {} slot {} points at {}, expected 0..{} (scan size)", p, k,
               point, num_points - 1);
    }
    const int32_t iy = pillars.cell(p, 0), ix = pillars.cell(p, 1);
    PS_CHECK(iy >= 0 && iy < height && ix >= 0 && ix < width,
             "decorate_points: pillar {} has cell (iy {}, ix {}) outside the {} x {} grid", p, iy,
             ix, height, width);
  }
  PS_FAIL("decorate_points: a pillar failed its checks once but not again");
}

// Decorates pillars [begin, end) into out (P', N, 10). kSlots: N when it is known at compile
// time, then each pillar's N rows are first zeroed by a fixed block of vector stores and the kept
// rows written over them while in L1; 0 for any N, then the padding rows are filled after the
// kept ones. Each pillar's count, cell and kept indices are checked as they are read (branches
// that are never taken on valid input cost next to nothing); returns false, having skipped the
// pillar at fault, if one is not valid.
template <int64_t kSlots>
bool decorate_range(std::span<const Point> points, const Pillars& pillars, const GridSpec& grid,
                    int64_t begin, int64_t end, float* out) {
  const int64_t slots = kSlots > 0 ? kSlots : pillars.point_index.dim(1);
  const int64_t pillar_floats = slots * kDecoratedFeatures;
  const auto num_points = static_cast<int64_t>(points.size());
  const int64_t width = grid.width(), height = grid.height();
  const double centre_z = grid.z_min + 0.5 * (grid.z_max - grid.z_min);
  const Point* point = points.data();
  bool valid = true;
  for (int64_t p = begin; p < end; ++p) {
    const int32_t* index = pillars.point_index.data() + p * slots;
    const int32_t count = pillars.count[p];
    const int32_t iy = pillars.cell[2 * p], ix = pillars.cell[2 * p + 1];
    bool kept_valid =
        count >= 0 && count <= slots && iy >= 0 && iy < height && ix >= 0 && ix < width;
    for (int32_t k = 0; kept_valid && k < count; ++k)
      kept_valid = index[k] >= 0 && index[k] < num_points;
    if (!kept_valid) {
      valid = false;
      continue;
    }
    const double centre_x = grid.x_min + (ix + 0.5) * grid.cell;
    const double centre_y = grid.y_min + (iy + 0.5) * grid.cell;
    float* rows = out + p * pillar_floats;
    if constexpr (kSlots > 0) {
      // Eigen's packet stores: a fill loop would become a `rep stos` or a memset call, each of
      // which costs more to start than the 13 64-byte stores of an 800-byte pillar.
      Eigen::Map<Eigen::Matrix<float, kSlots * kDecoratedFeatures, 1>>(rows).setZero();
    }
    // The features that need no mean, and the sums; then the offsets from the mean.
    float* row = rows;
    double sum_x = 0, sum_y = 0, sum_z = 0;
    for (int32_t k = 0; k < count; ++k, row += kDecoratedFeatures) {
      const Point& pt = point[index[k]];
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
    row = rows;
    for (int32_t k = 0; k < count; ++k, row += kDecoratedFeatures) {
      // From the points again (in L1 now): reading the row's x, y back as one load from two
      // fresh 4-byte stores would stall on store forwarding.
      const Point& pt = point[index[k]];
      row[4] = static_cast<float>(pt.x - mean_x);
      row[5] = static_cast<float>(pt.y - mean_y);
      row[6] = static_cast<float>(pt.z - mean_z);
    }
    // Padding rows right after the kept ones, so that each line of the output is written
    // once, while it is in cache.
    if constexpr (kSlots == 0) std::fill(row, rows + pillar_floats, 0.0f);
  }
  return valid;
}

}  // namespace

void decorate_points(std::span<const Point> points, const Pillars& pillars, const GridSpec& grid,
                     Tensor<float>& out) {
  check_shapes(pillars);
  const int64_t num_pillars = pillars.num_pillars();
  const int64_t slots = pillars.point_index.dim(1);
  // Keep the capacity of `out`: every element is written below.
  out.resize_for_overwrite({num_pillars, slots, kDecoratedFeatures});
  constexpr int64_t kPaperSlots = 20;  // N of the paper and of the default configuration
  std::vector<uint8_t> valid(static_cast<size_t>(num_threads()), 1);
  parallel_chunks(num_pillars, [&](int64_t begin, int64_t end, int t) {
    valid[static_cast<size_t>(t)] =
        slots == kPaperSlots
            ? decorate_range<kPaperSlots>(points, pillars, grid, begin, end, out.data())
            : decorate_range<0>(points, pillars, grid, begin, end, out.data());
  });
  if (std::find(valid.begin(), valid.end(), 0) != valid.end())
    throw_first_fault(points, pillars, grid);
}

Tensor<float> decorate_points(std::span<const Point> points, const Pillars& pillars,
                              const GridSpec& grid) {
  Tensor<float> out;
  decorate_points(points, pillars, grid, out);
  return out;
}

}  // namespace pillarseg::host
