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

#include "core/error.hpp"
#include "core/parallel.hpp"

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

namespace {

// The per-pillar lists of pass 1 and 2 (see PillarWorkspace), read by copy_out.
struct PillarLists {
  const int32_t* kept;       // (P'): pillar id of each kept pillar
  const int32_t* flat_cell;  // per pillar id: iy * W + ix
  const int32_t* begin;      // per pillar id: its first entry in members
  const int32_t* size;       // per pillar id: its number of points
  const int32_t* members;    // point indices grouped by pillar, N entries of slack at the end
};

// Writes kept pillars [begin, end) of `lists` into cell (P', 2), slots (P', N) and count (P').
// A pillar of at most N points is copied as one block of N (members[0 .. N) are readable thanks
// to the slack) with the slots past its size set to -1 by a mask, not a branch, so the copy
// stays one vector loop; a larger one keeps the members at select_positions (`positions`: N
// entries of scratch).
void copy_out(const PillarLists& lists, int64_t begin, int64_t end, int32_t slots_per_pillar,
              int32_t row_cells, SampleMode mode, Rng* rng, int32_t* positions, int32_t* cell,
              int32_t* slots, int32_t* count) {
  // iy = flat / W in doubles: the quotient of two integers below 2^31 is rounded correctly and
  // is never within rounding of the next integer, so truncating it is exact (and vectorises).
  const double row = row_cells;
  for (int64_t q = begin; q < end; ++q) {
    const int32_t flat_cell = lists.flat_cell[lists.kept[q]];
    const auto iy = static_cast<int32_t>(static_cast<double>(flat_cell) / row);
    cell[2 * q] = iy;
    cell[2 * q + 1] = flat_cell - iy * row_cells;
  }
  const int32_t n = slots_per_pillar;
  for (int64_t q = begin; q < end; ++q) {
    const int32_t pillar = lists.kept[q];
    const int32_t* members = lists.members + lists.begin[pillar];
    const int32_t size = lists.size[pillar];
    int32_t* row_slots = slots + q * n;
    if (size <= n) {
      for (int32_t k = 0; k < n; ++k) row_slots[k] = members[k] | -static_cast<int32_t>(k >= size);
      count[q] = size;
    } else {
      select_positions(size, n, mode, rng, positions);
      for (int32_t k = 0; k < n; ++k) row_slots[k] = members[positions[k]];
      count[q] = n;
    }
  }
}

// Passes 1 and 2 and the choice of pillars: ws.kept_pillars (P') and the per-pillar lists that
// write_pillars reads. Returns P'.
int64_t group_and_select(std::span<const Point> points, const GridSpec& grid,
                         const PillarConfig& cfg, SampleMode mode, Rng* rng,
                         PillarWorkspace& workspace) {
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

  // Pass 1a: flat cell iy * W + ix of each point, -1 outside the volume or with a reflectance
  // beyond kMaxAbsReflectance or NaN (non-finite coordinates fail the bounds). The test is
  // grid.contains() with the grid's numbers in locals and no branches, so the loop vectorises;
  // the floors are compared as doubles and only an inside point's floors are converted, so a
  // far or non-finite point is never converted to an integer.
  const auto row_cells = static_cast<int32_t>(width);
  ws.pillar_of_point.resize(points.size());
  parallel_chunks(num_points, [&](int64_t begin, int64_t end, int) {
    // Locals, not captures: a store to the int32 output could otherwise alias row_cells.
    const Point* point = points.data();
    int32_t* cell_of_point = ws.pillar_of_point.data();
    const double x_min = grid.x_min, x_max = grid.x_max, y_min = grid.y_min, y_max = grid.y_max;
    const double z_min = grid.z_min, z_max = grid.z_max, cell = grid.cell;
    const double cells_x = static_cast<double>(width), cells_y = static_cast<double>(height);
    const int32_t row = row_cells;
    for (int64_t i = begin; i < end; ++i) {
      const double x = point[i].x, y = point[i].y, z = point[i].z;
      const float r = point[i].r;
      const double fx = std::floor((x - x_min) / cell);
      const double fy = std::floor((y - y_min) / cell);
      // A NaN, infinite or absurd reflectance leaves the point out (kMaxAbsReflectance).
      const bool inside = (x >= x_min) & (x < x_max) & (y >= y_min) & (y < y_max) & (z >= z_min) &
                          (z < z_max) & (fx >= 0.0) & (fx < cells_x) & (fy >= 0.0) &
                          (fy < cells_y) & (std::fabs(r) <= kMaxAbsReflectance);
      const int32_t flat =
          static_cast<int32_t>(inside ? fy : 0.0) * row + static_cast<int32_t>(inside ? fx : 0.0);
      cell_of_point[i] = inside ? flat : -1;
    }
  });

  // Pass 1b: replace each cell by its pillar id, numbered by first appearance. The map is
  // marked dirty while in use, so a call interrupted by an exception makes the next one refill
  // it. There are at most min(M, W * H) pillars, so the per-pillar lists are sized once.
  const auto num_cells = static_cast<size_t>(width * height);
  if (!ws.cell_map_clean || ws.pillar_of_cell.size() != num_cells) {
    ws.pillar_of_cell.assign(num_cells, -1);
  }
  ws.cell_map_clean = false;
  const size_t max_pillars = std::min(points.size(), num_cells);
  if (ws.pillar_flat_cell.size() < max_pillars) ws.pillar_flat_cell.resize(max_pillars);
  if (ws.pillar_size.size() < max_pillars) ws.pillar_size.resize(max_pillars);
  int32_t num_found = 0;
  {
    int32_t* pillar_of_cell = ws.pillar_of_cell.data();
    int32_t* flat_cell = ws.pillar_flat_cell.data();
    int32_t* size = ws.pillar_size.data();
    int32_t* entry = ws.pillar_of_point.data();
    for (int32_t i = 0; i < num_points; ++i) {
      if (entry[i] < 0) continue;
      int32_t pillar = pillar_of_cell[entry[i]];
      if (pillar < 0) {
        pillar = num_found++;
        pillar_of_cell[entry[i]] = pillar;
        flat_cell[pillar] = entry[i];
        size[pillar] = 0;
      }
      ++size[pillar];
      entry[i] = pillar;
    }
    for (int32_t p = 0; p < num_found; ++p) pillar_of_cell[flat_cell[p]] = -1;
  }
  ws.cell_map_clean = true;
  const int64_t num_nonempty = num_found;

  // Pass 2: the points of each pillar in file order (counting sort), pillar p at
  // members[pillar_begin[p] .. pillar_begin[p + 1]).
  ws.pillar_begin.resize(static_cast<size_t>(num_nonempty) + 1);
  ws.pillar_begin[0] = 0;
  for (int64_t p = 0; p < num_nonempty; ++p) {
    ws.pillar_begin[p + 1] = ws.pillar_begin[p] + ws.pillar_size[p];
  }
  ws.cursor.assign(ws.pillar_begin.begin(), ws.pillar_begin.end() - 1);
  // N entries of slack at the end: a pillar's first N members can be read as one block.
  ws.members.resize(static_cast<size_t>(ws.pillar_begin.back()) + static_cast<size_t>(max_points));
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
  return num_kept;
}

// The kept pillars of group_and_select into cell (P', 2), point_index (P', N), count (P').
void write_pillars(const GridSpec& grid, const PillarConfig& cfg, SampleMode mode, Rng* rng,
                   PillarWorkspace& ws, int64_t num_kept, int32_t* cell, int32_t* point_index,
                   int32_t* count) {
  const int max_points = cfg.max_points_per_pillar;
  const auto row_cells = static_cast<int32_t>(grid.width());
  ws.positions.resize(static_cast<size_t>(max_points));
  const PillarLists lists{ws.kept_pillars.data(), ws.pillar_flat_cell.data(),
                          ws.pillar_begin.data(), ws.pillar_size.data(), ws.members.data()};
  if (mode == SampleMode::Inference) {
    // Evenly spaced positions draw nothing from rng: the pillars are independent.
    parallel_chunks(num_kept, [&](int64_t begin, int64_t end, int) {
      std::vector<int32_t> positions(static_cast<size_t>(max_points));
      copy_out(lists, begin, end, max_points, row_cells, mode, rng, positions.data(), cell,
               point_index, count);
    });
  } else {
    // Training draws each pillar's subset from rng in pillar order.
    copy_out(lists, 0, num_kept, max_points, row_cells, mode, rng, ws.positions.data(), cell,
             point_index, count);
  }
}

}  // namespace

void pillar_gather(std::span<const Point> points, const GridSpec& grid, const PillarConfig& cfg,
                   SampleMode mode, Rng* rng, PillarWorkspace& workspace, Pillars& out) {
  const int64_t num_kept = group_and_select(points, grid, cfg, mode, rng, workspace);
  // Every element of the output is written, padding included.
  out.cell.resize_for_overwrite({num_kept, 2});
  out.point_index.resize_for_overwrite({num_kept, cfg.max_points_per_pillar});
  out.count.resize_for_overwrite({num_kept});
  write_pillars(grid, cfg, mode, rng, workspace, num_kept, out.cell.data(), out.point_index.data(),
                out.count.data());
}

int64_t pillar_gather(std::span<const Point> points, const GridSpec& grid, const PillarConfig& cfg,
                      SampleMode mode, Rng* rng, PillarWorkspace& workspace,
                      const PillarRows& out) {
  PS_CHECK(out.capacity >= 0 && (out.capacity == 0 || (out.cell && out.point_index && out.count)),
           "pillar_gather: the output rows need cell, point_index and count memory for {} rows",
           out.capacity);
  const int64_t num_kept = group_and_select(points, grid, cfg, mode, rng, workspace);
  PS_CHECK(num_kept <= out.capacity,
           "pillar_gather: {} pillars do not fit the {} output rows given (P = {}, {} points)",
           num_kept, out.capacity, cfg.max_pillars, points.size());
  write_pillars(grid, cfg, mode, rng, workspace, num_kept, out.cell, out.point_index, out.count);
  return num_kept;
}

Pillars pillar_gather(std::span<const Point> points, const GridSpec& grid,
                      const PillarConfig& cfg, SampleMode mode, Rng* rng) {
  PillarWorkspace workspace;
  Pillars out;
  pillar_gather(points, grid, cfg, mode, rng, workspace, out);
  return out;
}

}  // namespace pillarseg::host
