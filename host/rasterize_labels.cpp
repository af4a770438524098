#include "host/rasterize_labels.hpp"

#include <algorithm>
#include <array>
#include <vector>

#include "core/error.hpp"

namespace pillarseg {

namespace {

// GridSpec::contains followed by GridSpec::cell_index, the same tests in the same double
// arithmetic, with one division per axis (those recompute W, H and the indices per call).
inline bool cell_of(const GridSpec& grid, int64_t width, int64_t height, const Point& p,
                    int64_t& cell) {
  const double x = p.x, y = p.y, z = p.z;
  if (!(x >= grid.x_min && x < grid.x_max && y >= grid.y_min && y < grid.y_max && z >= grid.z_min &&
        z < grid.z_max))
    return false;
  const int64_t ix = grid.ix(x), iy = grid.iy(y);
  if (ix < 0 || ix >= width || iy < 0 || iy >= height) return false;
  cell = iy * width + ix;
  return true;
}

// Counts only the cells that receive a point: a (cells x 13) count array would be 26 MB to
// clear per call at the default grid, while a scan touches about 40k of its 500k cells.
// slot_of_cell[c] is 1 + the row of cell c in `counts` (0: not touched yet). The rule is
// independent of point order, so the map is too.
template <class ClassOf>
Tensor<uint8_t> rasterize(std::span<const Point> points, ClassOf class_of, const ClassTable& table,
                          const GridSpec& grid) {
  const int width = grid.width(), height = grid.height();
  PS_CHECK(width > 0 && height > 0, "grid: expected at least one cell, got W = {}, H = {}", width,
           height);
  std::array<int64_t, kNumClassIds> weight{};  // weight[0] stays 0: unlabeled never wins
  for (int k = 1; k < kNumClassIds; ++k) weight[k] = table.gt_weight(k);

  using Counts = std::array<uint32_t, kNumClassIds>;
  std::vector<uint32_t> slot_of_cell(static_cast<size_t>(grid.cells()), 0);
  std::vector<int64_t> touched_cells;
  std::vector<Counts> counts;
  const size_t expected_touched = std::min(points.size(), static_cast<size_t>(grid.cells()));
  touched_cells.reserve(expected_touched);
  counts.reserve(expected_touched);

  for (size_t i = 0; i < points.size(); ++i) {
    const uint8_t k = class_of(i);
    if (weight[k] == 0) continue;
    int64_t cell = 0;
    if (!cell_of(grid, width, height, points[i], cell)) continue;
    uint32_t& slot = slot_of_cell[static_cast<size_t>(cell)];
    if (slot == 0) {
      touched_cells.push_back(cell);
      counts.push_back(Counts{});
      slot = static_cast<uint32_t>(counts.size());
    }
    ++counts[slot - 1][k];
  }

  Tensor<uint8_t> map({height, width});
  for (size_t s = 0; s < touched_cells.size(); ++s) {
    int64_t best_score = 0;
    uint8_t best_class = kUnlabeled;
    for (int k = 1; k < kNumClassIds; ++k) {
      const int64_t score = weight[k] * counts[s][k];
      if (score > best_score) {  // strict: a tie keeps the lower class id
        best_score = score;
        best_class = static_cast<uint8_t>(k);
      }
    }
    map[touched_cells[s]] = best_class;
  }
  return map;
}

}  // namespace

Tensor<uint8_t> rasterize_classes(std::span<const Point> points, std::span<const uint8_t> class_ids,
                                  const ClassTable& table, const GridSpec& grid) {
  PS_CHECK(class_ids.size() == points.size(),
           "rasterize_classes: expected one class id per point ({} points), got {} class ids",
           points.size(), class_ids.size());
  return rasterize(
      points,
      [&](size_t i) {
        const uint8_t k = class_ids[i];
        PS_CHECK(k < kNumClassIds, "rasterize_classes: point {} has class id {}, expected 0..{}", i,
                 k, kNumClassIds - 1);
        return k;
      },
      table, grid);
}

Tensor<uint8_t> rasterize_labels(std::span<const Point> points,
                                 std::span<const uint32_t> raw_labels, const ClassTable& table,
                                 const GridSpec& grid) {
  PS_CHECK(raw_labels.size() == points.size(),
           "rasterize_labels: expected one label per point ({} points), got {} labels",
           points.size(), raw_labels.size());
  return rasterize(
      points, [&](size_t i) { return table.class_of(raw_labels[i]); }, table, grid);
}

}  // namespace pillarseg
