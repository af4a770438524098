// Pillar gather: M points -> P' pillars of at most N points (see pillar_gather.hpp). Two passes
// over the points and no per-point allocation: pass 1 numbers the pillars through a W * H
// cell -> pillar map, pass 2 lists each pillar's points in file order (counting sort, CSR),
// then the kept pillars and points are copied out. The per-point cell test and, in
// Inference (no random draws), the copy-out run on all threads; each item writes only its own
// entries, so the result does not depend on the thread count.
#include "host/pillar_gather.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>
#include <vector>

#include "engine/core/error.hpp"
#include "engine/core/parallel.hpp"

namespace pillarseg::host {

void select_positions(int64_t n, int64_t keep, SampleMode mode, Rng* rng, int32_t* out) {
  PS_CHECK(keep >= 0 && keep <= n, "select_positions: need 0 <= keep <= n, given keep {} and n {}",
           keep, n);
  PS_CHECK(n <= std::numeric_limits<int32_t>::max(),
           "select_positions: n must fit int32 positions, given {}", n);
  if (keep == n) {  // nothing to drop: no random numbers are drawn
    std::iota(out, out + keep, int32_t{0});
    return;
  }
  if (mode == SampleMode::Inference) {
    // Evenly spaced over the whole list, so a pillar is not biased to the first lasers in the
    // file (the first-N rule of OpenPCDet's voxel generator would keep only those).
    for (int64_t k = 0; k < keep; ++k) out[k] = static_cast<int32_t>(k * n / keep);
    return;
  }
  PS_CHECK(rng != nullptr,
           "select_positions: Training mode draws a random subset and needs an Rng");
  // Algorithm S: item i is taken with probability (still needed) / (still available), which
  // makes every keep-subset equally likely and emits it in ascending order.
  int64_t taken = 0;
  for (int64_t i = 0; i < n && taken < keep; ++i) {
    const uint64_t available = static_cast<uint64_t>(n - i);
    if (rng->uniform_int(available) < static_cast<uint64_t>(keep - taken)) {
      out[taken++] = static_cast<int32_t>(i);
    }
  }
}

void pillar_gather(const std::vector<Point>& points, const GridSpec& grid, const PillarConfig& cfg,
                   SampleMode mode, Rng* rng, PillarWorkspace& workspace, Pillars& out) {
  const int max_points = cfg.max_points_per_pillar;
  PS_CHECK(max_points >= 1, "pillar_gather: max_points_per_pillar (N) must be >= 1, given {}",
           max_points);
  PS_CHECK(cfg.max_pillars >= 0,
           "pillar_gather: max_pillars (P) must be >= 0 (0 keeps every pillar), given {}",
           cfg.max_pillars);
  PS_CHECK(mode == SampleMode::Inference || rng != nullptr,
           "pillar_gather: Training mode samples at random and needs an Rng, given none");
  PS_CHECK(points.size() <= static_cast<size_t>(std::numeric_limits<int32_t>::max()),
           "pillar_gather: point indices are int32, so at most {} points, given {}",
           std::numeric_limits<int32_t>::max(), points.size());
  const int64_t width = grid.width(), height = grid.height();
  PS_CHECK(width >= 1 && height >= 1 && width * height <= std::numeric_limits<int32_t>::max(),
           "pillar_gather: the grid needs between 1 and 2^31 - 1 cells, given {} x {}", width,
           height);
  PillarWorkspace& ws = workspace;
  const auto num_points = static_cast<int32_t>(points.size());

  // Pass 1a: flat cell iy * W + ix of each point, -1 outside the volume. The test is
  // grid.contains() with W and H hoisted out of the loop; the floors are compared as doubles,
  // so a far or non-finite point is never converted to an integer.
  const double cells_x = static_cast<double>(width), cells_y = static_cast<double>(height);
  ws.pillar_of_point.resize(points.size());
  parallel_for(num_points, [&](int64_t i) {
    const double x = points[i].x, y = points[i].y, z = points[i].z;
    const double fx = std::floor((x - grid.x_min) / grid.cell);
    const double fy = std::floor((y - grid.y_min) / grid.cell);
    const bool inside = x >= grid.x_min && x < grid.x_max && y >= grid.y_min && y < grid.y_max &&
                        z >= grid.z_min && z < grid.z_max && fx >= 0.0 && fx < cells_x &&
                        fy >= 0.0 && fy < cells_y;
    ws.pillar_of_point[i] =
        inside ? static_cast<int32_t>(fy) * static_cast<int32_t>(width) + static_cast<int32_t>(fx)
               : -1;
  });

  // Pass 1b: replace each cell by its pillar id, numbered by first appearance. The map is
  // marked dirty while in use, so a call interrupted by an exception makes the next one refill
  // it.
  const auto num_cells = static_cast<size_t>(width * height);
  if (!ws.cell_map_clean || ws.pillar_of_cell.size() != num_cells) {
    ws.pillar_of_cell.assign(num_cells, -1);
  }
  ws.cell_map_clean = false;
  ws.pillar_flat_cell.clear();
  ws.pillar_size.clear();
  for (int32_t& entry : ws.pillar_of_point) {
    if (entry < 0) continue;
    int32_t& pillar = ws.pillar_of_cell[static_cast<size_t>(entry)];
    if (pillar < 0) {
      pillar = static_cast<int32_t>(ws.pillar_flat_cell.size());
      ws.pillar_flat_cell.push_back(entry);
      ws.pillar_size.push_back(0);
    }
    ++ws.pillar_size[static_cast<size_t>(pillar)];
    entry = pillar;
  }
  for (const int32_t flat_cell : ws.pillar_flat_cell) ws.pillar_of_cell[flat_cell] = -1;
  ws.cell_map_clean = true;
  const auto num_nonempty = static_cast<int64_t>(ws.pillar_flat_cell.size());

  // Pass 2: the points of each pillar in file order (counting sort), pillar p at
  // members[pillar_begin[p] .. pillar_begin[p + 1]).
  ws.pillar_begin.resize(static_cast<size_t>(num_nonempty) + 1);
  ws.pillar_begin[0] = 0;
  for (int64_t p = 0; p < num_nonempty; ++p) {
    ws.pillar_begin[p + 1] = ws.pillar_begin[p] + ws.pillar_size[p];
  }
  ws.cursor.assign(ws.pillar_begin.begin(), ws.pillar_begin.end() - 1);
  ws.members.resize(static_cast<size_t>(ws.pillar_begin.back()));
  for (int32_t i = 0; i < num_points; ++i) {
    const int32_t pillar = ws.pillar_of_point[i];
    if (pillar >= 0) ws.members[ws.cursor[pillar]++] = i;
  }

  // The pillars kept, in first-appearance order; in Training the pillar subset is drawn
  // before the point subsets.
  const int64_t num_kept =
      cfg.max_pillars > 0 ? std::min<int64_t>(num_nonempty, cfg.max_pillars) : num_nonempty;
  ws.kept_pillars.resize(static_cast<size_t>(num_kept));
  select_positions(num_nonempty, num_kept, mode, rng, ws.kept_pillars.data());

  // Every element of the output is written below, padding included.
  out.cell.resize_for_overwrite({num_kept, 2});
  out.point_index.resize_for_overwrite({num_kept, max_points});
  out.count.resize_for_overwrite({num_kept});
  ws.positions.resize(static_cast<size_t>(max_points));
  const auto row_cells = static_cast<int32_t>(width);
  const auto copy_out = [&](int64_t q, int32_t* positions) {
    const int32_t pillar = ws.kept_pillars[q];
    const int32_t flat_cell = ws.pillar_flat_cell[pillar];
    out.cell(q, 0) = flat_cell / row_cells;  // 32-bit division: cheaper than 64-bit
    out.cell(q, 1) = flat_cell % row_cells;
    const int32_t* pillar_points = ws.members.data() + ws.pillar_begin[pillar];
    const int32_t size = ws.pillar_size[pillar];
    int32_t* slots = &out.point_index(q, 0);
    if (size <= max_points) {
      std::copy(pillar_points, pillar_points + size, slots);
      std::fill(slots + size, slots + max_points, -1);
      out.count[q] = size;
    } else {
      select_positions(size, max_points, mode, rng, positions);
      for (int k = 0; k < max_points; ++k) slots[k] = pillar_points[positions[k]];
      out.count[q] = max_points;
    }
  };
  if (mode == SampleMode::Inference) {
    // Evenly spaced positions draw nothing from rng: the pillars are independent.
    parallel_chunks(num_kept, [&](int64_t begin, int64_t end, int) {
      std::vector<int32_t> positions(static_cast<size_t>(max_points));
      for (int64_t q = begin; q < end; ++q) copy_out(q, positions.data());
    });
  } else {
    // Training draws each pillar's subset from rng in pillar order.
    for (int64_t q = 0; q < num_kept; ++q) copy_out(q, ws.positions.data());
  }
}

Pillars pillar_gather(const std::vector<Point>& points, const GridSpec& grid,
                      const PillarConfig& cfg, SampleMode mode, Rng* rng) {
  PillarWorkspace workspace;
  Pillars out;
  pillar_gather(points, grid, cfg, mode, rng, workspace, out);
  return out;
}

}  // namespace pillarseg::host
