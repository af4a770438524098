// Ray walks through the top-view grid: single rays (ray_cells_2d, ray_voxels_3d), 3D occupancy
// counts (Z, H, W), and the 2D observability entry point (counted by raywalk_sweep.cpp);
// raywalk.hpp defines the walk exactly, raywalk_detail.hpp decides its crossings.
//
// How a ray is walked: it is cut into slabs across one axis (rows, or columns), and in each slab
// its cells form one run along the other axis, from the cell where it crosses into the slab to
// the cell where it crosses out (in 3D a run splits where the ray crosses a layer boundary). The
// cell at a crossing is a pure function of that crossing, decided exactly, not of the cells
// walked before; so any choice of slab axis gives the same cells, and a walk may start at any
// slab and still visit exactly the cells of the whole walk: this is what makes clipping to the
// grid, and splitting the grid into row bands between threads, exact.
//
// How voxels are counted: each thread owns a band of rows and walks the part of every ray inside
// it. A run adds to a difference array at its first voxel and subtracts after its last, so that
// it costs two updates whatever its length; prefix sums at the end turn differences into counts.
#include "host/raywalk.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include "core/error.hpp"
#include "core/parallel.hpp"
#include "host/raywalk_detail.hpp"

namespace pillarseg::host {
namespace {

using raywalk_detail::clamped_floor;
using raywalk_detail::CrossingCell;
using raywalk_detail::make_axis;
using raywalk_detail::RayAxis;

// Narrows [t0, t1] to where the ray lies within one cell of the cells [lo, hi) of this axis
// (t0 > t1 when it never does). The one-cell margin keeps rounding from losing a cell at the
// faces of the box; the walk itself decides which cells are visited.
void clip_to_cells(const RayAxis& axis, int64_t lo, int64_t hi, double& t0, double& t1) {
  if (axis.lo() >= lo && axis.hi() < hi) return;  // both ends inside: so is the whole ray
  if (axis.step == 0) {
    t1 = -1.0;
    return;
  }
  const double inverse = 1.0 / axis.delta;
  double ta = (static_cast<double>(lo - 1) - axis.origin) * inverse;
  double tb = (static_cast<double>(hi + 1) - axis.origin) * inverse;
  if (ta > tb) std::swap(ta, tb);
  t0 = std::max(t0, ta);
  t1 = std::min(t1, tb);
}

// Boundary of axis cell c crossed when leaving it with the given step: c + 1 upwards, c
// downwards (as a coordinate).
double exit_boundary(int64_t c, int64_t step) {
  return static_cast<double>(step > 0 ? c + 1 : c);
}
double entry_boundary(int64_t c, int64_t step) {
  return exit_boundary(c - step, step);
}

// A box of cells [x_lo, x_hi) x [y_lo, y_hi) x [z_lo, z_hi) the walk is restricted to.
struct CellBox {
  int64_t x_lo, x_hi, y_lo, y_hi, z_lo = 0, z_hi = 1;
};

// The grid's cell counts W, H and (for 3D walks) Z, computed once per call, as GridSpec computes
// them on each ask. A 2D walk is a walk through one layer.
struct GridSize {
  int64_t width, height, layers;
  GridSize(const GridSpec& grid, bool with_layers)
      : width(grid.width()), height(grid.height()), layers(with_layers ? grid.layers() : 1) {}
};

// The w axis of a 2D walk: one layer, never crossed.
RayAxis flat_axis() {
  return make_axis(0.5, 0.5, 1);
}

// Buffers for the crossings of one ray, reused from ray to ray (one set per thread).
struct WalkScratch {
  explicit WalkScratch(const GridSize& size)
      : run_exits(static_cast<size_t>(std::max(size.width, size.height)) + 3),
        layer_exits(run_exits.size()) {}
  std::vector<double> run_exits;    // where the ray leaves each slab, along the run axis
  std::vector<double> layer_exits;  // layer where the ray leaves each slab
};

// Calls run(slab, layer, from, to) for the cells of the walk of (u, v, w) inside the box's slab
// range, in walk order. The walk is cut into slabs across the run axis, which is x when
// kRunsAlongX (slabs are rows, cells (from..to, slab)), else y (slabs are columns, cells
// (slab, from..to)); runs are not cut to the box along the run axis nor in z. In each slab the
// ray's cells form one run along the run axis, from where it crosses into the slab to where it
// crosses out; where it crosses layer boundaries within the slab, the run splits at the cell of
// each crossing, which both parts share. Runs along the axis the ray moves most along are the
// longest and fewest.
template <bool kRunsAlongX, bool kThreeD, class Run>
void walk_runs(const RayAxis& u, const RayAxis& v, const RayAxis& w, const GridSize& size,
               const CellBox& box, WalkScratch& scratch, Run&& run) {
  double t0 = 0.0, t1 = 1.0;
  clip_to_cells(u, box.x_lo, box.x_hi, t0, t1);
  clip_to_cells(v, box.y_lo, box.y_hi, t0, t1);
  if constexpr (kThreeD) clip_to_cells(w, box.z_lo, box.z_hi, t0, t1);
  if (t0 > t1) return;
  const RayAxis& across = kRunsAlongX ? v : u;  // the slab axis
  const RayAxis& along = kRunsAlongX ? u : v;   // the run axis
  const int64_t across_cells = kRunsAlongX ? size.height : size.width;
  const int64_t along_cells = kRunsAlongX ? size.width : size.height;
  // The slabs in the box that may hold cells of the ray for t in [t0, t1], with one slab of
  // margin on both sides: the range only bounds the walk, the crossings decide its cells.
  const double at_t0 = across.origin + t0 * across.delta, at_t1 = across.origin + t1 * across.delta;
  const int64_t lo = std::max({clamped_floor(std::min(at_t0, at_t1), across_cells) - 1, across.lo(),
                               kRunsAlongX ? box.y_lo : box.x_lo});
  const int64_t hi = std::min({clamped_floor(std::max(at_t0, at_t1), across_cells) + 1, across.hi(),
                               (kRunsAlongX ? box.y_hi : box.x_hi) - 1});
  if (lo > hi) return;
  const int64_t step = across.step >= 0 ? 1 : -1;
  const int64_t first = step > 0 ? lo : hi, slabs = hi - lo + 1;
  const bool starts_here = first == across.first, ends_here = (step > 0 ? hi : lo) == across.last;
  // Where the ray leaves each slab: run_exits[i] along the run axis (x steps before y at a tie).
  const CrossingCell along_at_slab(along, across, /*m_steps_first=*/kRunsAlongX, along_cells);
  double* run_exits = scratch.run_exits.data();
  along_at_slab.fill(exit_boundary(first, step), static_cast<double>(step),
                     slabs - (ends_here ? 1 : 0), run_exits);
  if (ends_here) run_exits[slabs - 1] = static_cast<double>(along.last);
  int64_t cell = starts_here ? along.first : along_at_slab.at(entry_boundary(first, step));
  if constexpr (!kThreeD) {
    for (int64_t i = 0; i < slabs; ++i) {
      const auto cell_out = static_cast<int64_t>(run_exits[i]);
      run(first + i * step, int64_t{0}, cell, cell_out);
      cell = cell_out;
    }
  } else {
    // The layer where the ray leaves each slab (z steps after x and y at a tie), and the cell
    // along the run axis where it crosses a layer boundary (x and y step first).
    const CrossingCell layer_at_slab(w, across, /*m_steps_first=*/false, size.layers);
    const CrossingCell along_at_layer(along, w, /*m_steps_first=*/true, along_cells);
    double* layer_exits = scratch.layer_exits.data();
    layer_at_slab.fill(exit_boundary(first, step), static_cast<double>(step),
                       slabs - (ends_here ? 1 : 0), layer_exits);
    if (ends_here) layer_exits[slabs - 1] = static_cast<double>(w.last);
    int64_t layer = starts_here ? w.first : layer_at_slab.at(entry_boundary(first, step));
    for (int64_t i = 0; i < slabs; ++i) {
      const int64_t slab = first + i * step;
      const auto cell_out = static_cast<int64_t>(run_exits[i]);
      const auto layer_out = static_cast<int64_t>(layer_exits[i]);
      for (; (layer_out - layer) * w.step > 0; layer += w.step) {
        const int64_t cell_at = along_at_layer.at(exit_boundary(layer, w.step));
        run(slab, layer, cell, cell_at);
        cell = cell_at;
      }
      run(slab, layer, cell, cell_out);
      cell = cell_out;
    }
  }
}

// Calls cell(ix, iy, iz) for the cells of the walk inside the box, in walk order.
template <bool kRunsAlongX, bool kThreeD, class Cell>
void walk_cells_along(const RayAxis& u, const RayAxis& v, const RayAxis& w, const GridSize& size,
                      const CellBox& box, WalkScratch& scratch, Cell&& cell) {
  const auto run_cells = [&](int64_t slab, int64_t layer, int64_t from, int64_t to) {
    if (layer < box.z_lo || layer >= box.z_hi) return;
    const int64_t step = to >= from ? 1 : -1;
    for (int64_t i = from;; i += step) {
      if constexpr (kRunsAlongX) {
        if (i >= box.x_lo && i < box.x_hi) cell(i, slab, layer);
      } else {
        if (i >= box.y_lo && i < box.y_hi) cell(slab, i, layer);
      }
      if (i == to) break;
    }
  };
  walk_runs<kRunsAlongX, kThreeD>(u, v, w, size, box, scratch, run_cells);
}

template <bool kThreeD, class Cell>
void walk_cells(const RayAxis& u, const RayAxis& v, const RayAxis& w, const GridSize& size,
                const CellBox& box, WalkScratch& scratch, Cell&& cell) {
  if (std::abs(u.delta) >= std::abs(v.delta)) {
    walk_cells_along<true, kThreeD>(u, v, w, size, box, scratch, cell);
  } else {
    walk_cells_along<false, kThreeD>(u, v, w, size, box, scratch, cell);
  }
}

// Counts (Z, H, W) kept as differences along x while rays are walked, so that a run costs two
// updates whatever its length: a run of columns c0..c1 of a row adds its weight at c0 and takes
// it at c1 + 1 (where c1 + 1 < W). Sums are mod 2^32, exact while the counts fit uint32. kCut: the
// run may reach beyond the grid (or volume) and is cut to it; else it lies inside.
struct RunCounts {
  uint32_t* counts;
  int64_t width, height, layers;

  template <bool kCut>
  void add(int64_t row, int64_t layer, int64_t from, int64_t to, uint32_t weight) const {
    int64_t lo = std::min(from, to), hi = std::max(from, to);
    if constexpr (kCut) {
      lo = std::max<int64_t>(lo, 0);
      hi = std::min(hi, width - 1);
      if (lo > hi || layer < 0 || layer >= layers) return;
    }
    uint32_t* line = counts + (layer * height + row) * width;
    line[lo] += weight;
    if (hi + 1 < width) line[hi + 1] -= weight;
  }

  // Turns the differences of the rows [row_lo, row_hi) of every layer into counts.
  void finish(int64_t row_lo, int64_t row_hi) const {
    for (int64_t layer = 0; layer < layers; ++layer) {
      for (int64_t row = row_lo; row < row_hi; ++row) {
        uint32_t* line = counts + (layer * height + row) * width;
        uint32_t running = 0;
        for (int64_t c = 0; c < width; ++c) line[c] = running += line[c];
      }
    }
  }
};

// Adds the voxels of one ray's walk inside the box to the run counts, with runs along x.
template <bool kCut>
void count_walk(const RayAxis& u, const RayAxis& v, const RayAxis& w, const GridSize& size,
                const CellBox& box, WalkScratch& scratch, const RunCounts& runs) {
  const auto add = [&runs](int64_t row, int64_t layer, int64_t from, int64_t to) {
    runs.add<kCut>(row, layer, from, to, 1);
  };
  walk_runs<true, true>(u, v, w, size, box, scratch, add);
}

void check_grid(const GridSpec& grid, bool with_layers, const char* caller) {
  constexpr int64_t kMaxCells = int64_t{1} << 24;
  PS_CHECK(std::isfinite(grid.cell) && grid.cell > 0.0,
           "{}: grid cell must be a positive size, got {}", caller, grid.cell);
  PS_CHECK(std::isfinite(grid.x_min) && std::isfinite(grid.y_min) && std::isfinite(grid.z_min),
           "{}: grid minimum must be finite, got ({}, {}, {})", caller, grid.x_min, grid.y_min,
           grid.z_min);
  PS_CHECK(grid.width() >= 1 && grid.width() <= kMaxCells && grid.height() >= 1 &&
               grid.height() <= kMaxCells,
           "{}: grid must have 1 to {} cells per axis, got W = {}, H = {}", caller, kMaxCells,
           grid.width(), grid.height());
  if (with_layers) {
    PS_CHECK(std::isfinite(grid.voxel_z) && grid.voxel_z > 0.0,
             "{}: grid voxel_z must be a positive size, got {}", caller, grid.voxel_z);
    PS_CHECK(grid.layers() >= 1 && grid.layers() <= kMaxCells,
             "{}: grid must have 1 to {} layers, got Z = {}", caller, kMaxCells, grid.layers());
  }
}

void check_origin(const Eigen::Vector3d& origin, const char* caller) {
  PS_CHECK(origin.allFinite(), "{}: sensor origin must be finite, got ({}, {}, {})", caller,
           origin.x(), origin.y(), origin.z());
}

void check_point_count(size_t count, const char* caller) {
  PS_CHECK(count <= std::numeric_limits<uint32_t>::max(),
           "{}: at most {} points fit the uint32 counts, got {}", caller,
           std::numeric_limits<uint32_t>::max(), count);
}

bool finite(const Point& p) {
  return std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z);
}

// Cell coordinates of a position, as the walk uses them (w only for 3D walks).
struct CellCoordinates {
  double u, v, w;
};
CellCoordinates cell_coordinates(double x, double y, double z, const GridSpec& grid, bool with_w) {
  return {(x - grid.x_min) / grid.cell, (y - grid.y_min) / grid.cell,
          with_w ? (z - grid.z_min) / grid.voxel_z : 0.0};
}

// GridSpec::contains_xy, reusing the point's cells u.last, v.last (floor((x - x_min) / cell) etc.).
bool contains_xy(const Point& p, const GridSpec& grid, const GridSize& size, const RayAxis& u,
                 const RayAxis& v) {
  return p.x >= grid.x_min && p.x < grid.x_max && p.y >= grid.y_min && p.y < grid.y_max &&
         u.last >= 0 && u.last < size.width && v.last >= 0 && v.last < size.height;
}

// GridSpec::contains, likewise.
bool contains(const Point& p, const GridSpec& grid, const GridSize& size, const RayAxis& u,
              const RayAxis& v, const RayAxis& w) {
  return contains_xy(p, grid, size, u, v) && p.z >= grid.z_min && p.z < grid.z_max && w.last >= 0 &&
         w.last < size.layers;
}

// Row bands [bounds[t], bounds[t + 1]) of the grid, one per thread, cut so that each holds about
// the same number of (ray, row) pairs, the unit of walk work. The counts do not depend on the
// cut, only the balance does.
std::vector<int64_t> balanced_row_bands(std::span<const Point> points,
                                        const CellCoordinates& origin, const GridSpec& grid,
                                        int threads) {
  const int64_t height = grid.height();
  std::vector<int64_t> bounds(static_cast<size_t>(threads) + 1, height);
  bounds[0] = 0;
  if (threads == 1) return bounds;
  // Per thread, a difference array over the rows: a ray spans rows lo..hi.
  std::vector<std::vector<int64_t>> partial(
      static_cast<size_t>(threads), std::vector<int64_t>(static_cast<size_t>(height) + 1, 0));
  parallel_chunks(static_cast<int64_t>(points.size()), [&](int64_t begin, int64_t end, int t) {
    std::vector<int64_t>& diff = partial[static_cast<size_t>(t)];
    for (int64_t i = begin; i < end; ++i) {
      const Point& p = points[static_cast<size_t>(i)];
      if (!finite(p)) continue;
      const RayAxis v = make_axis(origin.v, (p.y - grid.y_min) / grid.cell, height);
      const int64_t lo = std::max<int64_t>(v.lo(), 0), hi = std::min<int64_t>(v.hi(), height - 1);
      if (lo > hi) continue;
      ++diff[static_cast<size_t>(lo)];
      --diff[static_cast<size_t>(hi) + 1];
    }
  });
  std::vector<int64_t> work(static_cast<size_t>(height), 0);  // work of rows 0..r
  int64_t rays = 0, total = 0;
  for (int64_t r = 0; r < height; ++r) {
    for (const std::vector<int64_t>& diff : partial) rays += diff[static_cast<size_t>(r)];
    total += rays;
    work[static_cast<size_t>(r)] = total;
  }
  int64_t r = 0;
  for (int t = 1; t < threads; ++t) {
    while (r < height && work[static_cast<size_t>(r)] * threads < total * t) ++r;
    bounds[static_cast<size_t>(t)] =
        std::max(bounds[static_cast<size_t>(t) - 1], std::min(r + 1, height));
  }
  return bounds;
}

// Walks every ray of the scan through the volume and counts, per voxel of `passes` (Z, H, W),
// the rays that pass it before their end voxel, and per voxel of `hits` the rays that end in it
// with the point inside the volume (GridSpec::contains). One band of rows per thread: every
// thread walks the part of each ray inside its band. Runs go along x (a second difference array
// along y, as the 2D sweeps use, would cost Z times the grid), so steep rays make rows of one or
// two voxels.
void count_rays_3d(std::span<const Point> points, const Eigen::Vector3d& origin,
                   const GridSpec& grid, const GridSize& size, uint32_t* passes, uint32_t* hits) {
  const CellCoordinates o = cell_coordinates(origin.x(), origin.y(), origin.z(), grid, true);
  const std::vector<int64_t> bands = balanced_row_bands(points, o, grid, num_threads());
  const RunCounts runs{passes, size.width, size.height, size.layers};
  parallel_for(static_cast<int64_t>(bands.size()) - 1, [&](int64_t band) {
    const CellBox box{
        0, size.width, bands[static_cast<size_t>(band)], bands[static_cast<size_t>(band) + 1],
        0, size.layers};
    if (box.y_lo >= box.y_hi) return;
    WalkScratch scratch(size);
    for (const Point& p : points) {
      if (!finite(p)) continue;
      const CellCoordinates point = cell_coordinates(p.x, p.y, p.z, grid, true);
      const RayAxis v = make_axis(o.v, point.v, size.height);
      if (v.hi() < box.y_lo || v.lo() >= box.y_hi) continue;
      const RayAxis u = make_axis(o.u, point.u, size.width);
      const RayAxis w = make_axis(o.w, point.w, size.layers);
      // Runs need cutting only where the ray's voxels reach beyond the volume along them.
      if (u.lo() >= 0 && u.hi() < size.width && w.lo() >= 0 && w.hi() < size.layers) {
        count_walk<false>(u, v, w, size, box, scratch, runs);
      } else {
        count_walk<true>(u, v, w, size, box, scratch, runs);
      }
      // The walk's last voxel is the end voxel, which counts a hit, not a pass.
      const bool end_in_box = u.last >= 0 && u.last < size.width && v.last >= box.y_lo &&
                              v.last < box.y_hi && w.last >= 0 && w.last < size.layers;
      if (!end_in_box) continue;
      runs.add<false>(v.last, w.last, u.last, u.last, static_cast<uint32_t>(-1));
      if (contains(p, grid, size, u, v, w))
        ++hits[(w.last * size.height + v.last) * size.width + u.last];
    }
    runs.finish(box.y_lo, box.y_hi);
  });
}

// The occupancy probability of a voxel with `hits` and `passes`, as specified.
float probability_of(uint32_t hits, uint32_t passes) {
  if (hits == 0 && passes == 0) return 0.5f;
  const double log_odds = hits * std::log(0.7 / 0.3) + passes * std::log(0.4 / 0.6);
  return static_cast<float>(1.0 / (1.0 + std::exp(-log_odds)));
}

}  // namespace

ObservabilityCounts observability_2d(std::span<const Point> points,
                                     const Eigen::Vector3d& origin, const GridSpec& grid) {
  ObservabilityWorkspace workspace;
  ObservabilityCounts counts;
  observability_2d(points, origin, grid, workspace, counts);
  return counts;
}

void observability_2d(std::span<const Point> points, const Eigen::Vector3d& origin,
                      const GridSpec& grid, ObservabilityWorkspace& workspace,
                      ObservabilityCounts& out) {
  constexpr const char* kCaller = "observability_2d";
  check_grid(grid, false, kCaller);
  check_origin(origin, kCaller);
  check_point_count(points.size(), kCaller);
  const GridSize size(grid, false);
  out.transmissions.resize({size.height, size.width});
  out.detections.resize({size.height, size.width});
  const CellCoordinates o = cell_coordinates(origin.x(), origin.y(), origin.z(), grid, false);
  raywalk_detail::count_observability_2d(points, o.u, o.v, grid, workspace.buffers(),
                                         out.transmissions.data(), out.detections.data());
}

Tensor<uint32_t> observability_map(const ObservabilityCounts& counts) {
  PS_CHECK(
      counts.transmissions.rank() == 2 && counts.transmissions.shape() == counts.detections.shape(),
      "observability_map: transmissions and detections must both be (H, W), got {} and {}",
      shape_str(counts.transmissions.shape()), shape_str(counts.detections.shape()));
  Tensor<uint32_t> map(counts.transmissions.shape());
  for (int64_t i = 0; i < map.numel(); ++i) map[i] = counts.transmissions[i] + counts.detections[i];
  return map;
}

OccupancyCounts occupancy_counts_3d(std::span<const Point> points, const Eigen::Vector3d& origin,
                                    const GridSpec& grid) {
  constexpr const char* kCaller = "occupancy_counts_3d";
  check_grid(grid, true, kCaller);
  check_origin(origin, kCaller);
  check_point_count(points.size(), kCaller);
  const GridSize size(grid, true);
  OccupancyCounts counts{Tensor<uint32_t>::zeros({size.layers, size.height, size.width}),
                         Tensor<uint32_t>::zeros({size.layers, size.height, size.width})};
  count_rays_3d(points, origin, grid, size, counts.passes.data(), counts.hits.data());
  return counts;
}

Tensor<float> occupancy_probability(const OccupancyCounts& counts) {
  PS_CHECK(counts.hits.rank() == 3 && counts.hits.shape() == counts.passes.shape(),
           "occupancy_probability: hits and passes must both be (Z, H, W), got {} and {}",
           shape_str(counts.hits.shape()), shape_str(counts.passes.shape()));
  // Most voxels have few hits and passes: their probabilities come from a table of the same
  // formula (so the same values), the rest from the formula.
  constexpr uint32_t kTableHits = 16, kTablePasses = 256;
  std::vector<float> table(kTableHits * kTablePasses);
  for (uint32_t h = 0; h < kTableHits; ++h)
    for (uint32_t p = 0; p < kTablePasses; ++p) table[h * kTablePasses + p] = probability_of(h, p);
  Tensor<float> probability(counts.hits.shape());
  const uint32_t* hits = counts.hits.data();
  const uint32_t* passes = counts.passes.data();
  float* out = probability.data();
  parallel_for(probability.numel(), [&](int64_t i) {
    const uint32_t h = hits[i], p = passes[i];
    out[i] =
        h < kTableHits && p < kTablePasses ? table[h * kTablePasses + p] : probability_of(h, p);
  });
  return probability;
}

std::vector<WalkCell> ray_cells_2d(const Eigen::Vector3d& origin, const Eigen::Vector3d& point,
                                   const GridSpec& grid) {
  check_grid(grid, false, "ray_cells_2d");
  check_origin(origin, "ray_cells_2d");
  PS_CHECK(point.allFinite(), "ray_cells_2d: point must be finite, got ({}, {}, {})", point.x(),
           point.y(), point.z());
  const GridSize size(grid, false);
  const CellCoordinates o = cell_coordinates(origin.x(), origin.y(), origin.z(), grid, false);
  const CellCoordinates p = cell_coordinates(point.x(), point.y(), point.z(), grid, false);
  std::vector<WalkCell> cells;
  WalkScratch scratch(size);
  walk_cells<false>(make_axis(o.u, p.u, size.width), make_axis(o.v, p.v, size.height), flat_axis(),
                    size, CellBox{0, size.width, 0, size.height}, scratch,
                    [&](int64_t ix, int64_t iy, int64_t) {
                      cells.push_back({ix, iy, 0});
                    });
  return cells;
}

std::vector<WalkCell> ray_voxels_3d(const Eigen::Vector3d& origin, const Eigen::Vector3d& point,
                                    const GridSpec& grid) {
  check_grid(grid, true, "ray_voxels_3d");
  check_origin(origin, "ray_voxels_3d");
  PS_CHECK(point.allFinite(), "ray_voxels_3d: point must be finite, got ({}, {}, {})", point.x(),
           point.y(), point.z());
  const GridSize size(grid, true);
  const CellCoordinates o = cell_coordinates(origin.x(), origin.y(), origin.z(), grid, true);
  const CellCoordinates p = cell_coordinates(point.x(), point.y(), point.z(), grid, true);
  std::vector<WalkCell> voxels;
  WalkScratch scratch(size);
  walk_cells<true>(make_axis(o.u, p.u, size.width), make_axis(o.v, p.v, size.height),
                   make_axis(o.w, p.w, size.layers), size,
                   CellBox{0, size.width, 0, size.height, 0, size.layers}, scratch,
                   [&](int64_t ix, int64_t iy, int64_t iz) {
                     voxels.push_back({ix, iy, iz});
                   });
  return voxels;
}

}  // namespace pillarseg::host
