// 2D observability counts (H, W) by slab sweeps; raywalk.hpp defines the walk, and these counts
// are those of single-ray walks (tests/test_raywalk.cpp checks them against ray_cells_2d).
//
// All rays of a scan leave one origin. A ray that moves at least as far along x as along y is
// counted row by row (a "row ray"), any other column by column. In one row, a row ray's cells form
// one run along x, from the cell where it enters the row to the cell where it leaves it; each
// crossing is decided exactly by CrossingCell, a pure function of the ray and the boundary. The
// crossing where a ray leaves a row is the one where it enters the next, so each is counted once,
// per cell and direction, in rows small enough to stay in the L1 cache, and a row's runs follow
// from the counts at its two boundaries (SweepScratch). The row rays that leave the origin's row
// upwards are sorted by their last row, highest first, so that the rays reaching any row are a
// prefix of them and a row's crossings are one vectorised pass over that prefix; likewise
// downwards, and for column rays rightwards and leftwards. A pass per point, also vectorised,
// sorts the rays into these four sweeps. Rows are dealt out in bands, one per thread, each
// holding about the same number of (ray, row) pairs; then columns likewise. Every cell's count is
// a sum of integers made by the one thread that owns its row (then column), so the counts are the
// same for every thread count.
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <memory>

#include "core/parallel.hpp"
#include "host/raywalk.hpp"
#include "host/raywalk_detail.hpp"

namespace pillarseg::host::raywalk_detail {
namespace {

// How one family of sweeps lies on the grid: slabs are rows (runs along x) or columns (runs
// along y); the run axis is the other one.
struct Orientation {
  int64_t slabs = 0;         // slab count: H for rows, W for columns
  int64_t cells = 0;         // cells along the run axis: W for rows, H for columns
  double slab_origin = 0.0;  // the origin in cell coordinates, across and along the slabs
  double run_origin = 0.0;
  bool run_steps_first = false;  // at a tie the run axis steps first (x steps before y)
  double window = 0.0;           // CrossingCell's tie window for the run axis
  bool runs_along_x = false;     // slabs are rows
  const GridSpec* grid = nullptr;
  const Point* points = nullptr;  // the scan, which the sweeps' rays index

  // A point in cell coordinates along the run axis and across the slabs, as the walk computes
  // them ((x - x_min) / cell etc.).
  double run_end(const Point& p) const {
    return runs_along_x ? (p.x - grid->x_min) / grid->cell : (p.y - grid->y_min) / grid->cell;
  }
  double slab_end(const Point& p) const {
    return runs_along_x ? (p.y - grid->y_min) / grid->cell : (p.x - grid->x_min) / grid->cell;
  }
};

// The rays that leave the origin's slab in one direction across the slabs, in structure-of-arrays
// form, those that reach the farthest slab first.
struct Sweep {
  int step = 1;       // +1 or -1 across the slabs
  int64_t first = 0;  // the slab all its rays start in, clamped to [-1, slabs]
  // Per ray, in sweep order:
  std::vector<double> slope;        // run-axis change per unit across the slabs
  std::vector<int32_t> first_cell;  // run-axis cell where the ray leaves the origin
  std::vector<int32_t> last_cell;   // run-axis cell of the end point, clamped to [-1, cells]
  std::vector<uint32_t> point;      // the ray's point (for the rare exact tie)
  std::vector<uint8_t> in_range;    // the point lies in the grid's x and y range (a detection)
  // reaching[d]: the rays that reach slab first + d * step, d = 0 .. slabs + 1 (a prefix).
  std::vector<int64_t> reaching;

  void resize(int64_t rays) {
    const auto n = static_cast<size_t>(rays);
    slope.resize(n);
    first_cell.resize(n);
    last_cell.resize(n);
    point.resize(n);
    in_range.resize(n);
  }

  // Slabs a ray of the sweep ending in slab `last` crosses after the first: its depth.
  int64_t depth(int64_t last) const { return (last - first) * step; }

  // Rays that reach `slab` (0 for slabs the sweep never reaches).
  int64_t reaching_slab(int64_t slab) const {
    const int64_t d = depth(slab);
    return d >= 0 && d < static_cast<int64_t>(reaching.size()) ? reaching[static_cast<size_t>(d)]
                                                               : 0;
  }
};

// The four sweeps: rows upwards (and rays within the origin's row), rows downwards, columns
// rightwards (and rays within the origin's column), columns leftwards.
enum SweepIndex { kRowsUp = 0, kRowsDown = 1, kColumnsRight = 2, kColumnsLeft = 3, kSweeps = 4 };

// Each point's ray, classified: its sweep (kSweeps for a point that is not finite) and depth,
// and what its sweep keeps of it. Point order.
struct RayClasses {
  std::vector<uint8_t> sweep;
  std::vector<int32_t> depth;
  std::vector<double> slope;        // run-axis change per unit across the slabs
  std::vector<int32_t> first_cell;  // run-axis cell where the ray leaves the origin
  std::vector<int32_t> last_cell;   // run-axis cell of the end point, clamped to [-1, cells]
  std::vector<uint8_t> in_range;    // the point lies in the grid's x and y range

  void resize(size_t n) {
    sweep.resize(n);
    depth.resize(n);
    slope.resize(n);
    first_cell.resize(n);
    last_cell.resize(n);
    in_range.resize(n);
  }
};

// Classifies points [begin, end): a ray that moves at least as far along x as along y is a row
// ray (rows upwards when it does not move down, else downwards), any other a column ray
// (rightwards when it does not move left). The values are those of make_axis and
// CrossingCell::slope, computed without branches (selects, and floors clamped in double) so that
// the loop vectorises (the outputs are declared not to alias, else the compiler gives up on the
// number of overlap checks).
void classify_rays(const Point* __restrict point, int64_t begin, int64_t end, const GridSpec& grid,
                   const std::array<Orientation, 2>& orientation, uint8_t* __restrict sweep_of,
                   int32_t* __restrict depth_of, double* __restrict slope,
                   int32_t* __restrict first_cell, int32_t* __restrict last_cell,
                   uint8_t* __restrict in_range) {
  const double x_min = grid.x_min, x_max = grid.x_max, y_min = grid.y_min, y_max = grid.y_max;
  const double cell = grid.cell;
  const double origin_u = orientation[0].run_origin, origin_v = orientation[0].slab_origin;
  const auto width = static_cast<double>(orientation[0].cells);
  const auto height = static_cast<double>(orientation[0].slabs);
  // make_axis's first cell per axis and direction; across the slabs, that is the sweep's first
  // slab (build_sweeps).
  const auto first_u_up = static_cast<double>(clamped_floor(origin_u, orientation[0].cells));
  const auto first_u_down =
      static_cast<double>(clamped_floor(std::ceil(origin_u) - 1.0, orientation[0].cells));
  const auto first_v_up = static_cast<double>(clamped_floor(origin_v, orientation[0].slabs));
  const auto first_v_down =
      static_cast<double>(clamped_floor(std::ceil(origin_v) - 1.0, orientation[0].slabs));
  constexpr double kLargest = std::numeric_limits<float>::max();
  for (int64_t i = begin; i < end; ++i) {
    const double px = point[i].x, py = point[i].y, pz = point[i].z;
    const bool finite =
        (std::abs(px) <= kLargest) & (std::abs(py) <= kLargest) & (std::abs(pz) <= kLargest);
    const double u_end = (px - x_min) / cell, v_end = (py - y_min) / cell;
    const double du = u_end - origin_u, dv = v_end - origin_v;
    const bool row = std::abs(du) >= std::abs(dv);
    // Across the slabs (a) and along the runs (m).
    const double a_end = row ? v_end : u_end, a_origin = row ? origin_v : origin_u;
    const double a_delta = row ? dv : du, a_cells = row ? height : width;
    const double m_end = row ? u_end : v_end, m_origin = row ? origin_u : origin_v;
    const double m_delta = row ? du : dv, m_cells = row ? width : height;
    const bool a_forward = a_end >= a_origin;  // step >= 0
    const int sweep =
        row ? (a_forward ? kRowsUp : kRowsDown) : (a_forward ? kColumnsRight : kColumnsLeft);
    const double a_last = std::min(std::max(std::floor(a_end), -1.0), a_cells);
    const double first_slab =
        row ? (a_forward ? first_v_up : first_v_down) : (a_forward ? first_u_up : first_u_down);
    const double depth = (a_last - first_slab) * (a_forward ? 1.0 : -1.0);
    const bool m_backward = m_end < m_origin;  // step < 0
    const double m_first =
        row ? (m_backward ? first_u_down : first_u_up) : (m_backward ? first_v_down : first_v_up);
    const double m_last = std::min(std::max(std::floor(m_end), -1.0), m_cells);
    sweep_of[i] = static_cast<uint8_t>(finite ? sweep : kSweeps);
    depth_of[i] = static_cast<int32_t>(finite ? depth : 0.0);
    slope[i] = a_delta != 0.0 ? m_delta / a_delta : 0.0;
    first_cell[i] = static_cast<int32_t>(m_first);
    last_cell[i] = static_cast<int32_t>(finite ? m_last : 0.0);
    in_range[i] = (px >= x_min) & (px < x_max) & (py >= y_min) & (py < y_max);
  }
}

// Sorts the finite points' rays into the four sweeps. Each thread classifies a contiguous chunk
// of the points and counts its rays per (sweep, depth); a ray's place depends on the counts only,
// so the order is the same for every thread count.
void build_sweeps(std::span<const Point> points, const GridSpec& grid,
                  const std::array<Orientation, 2>& orientation, std::array<Sweep, kSweeps>& sweeps,
                  std::vector<std::array<std::vector<int64_t>, kSweeps>>& counts,
                  RayClasses& classes) {
  for (int s = 0; s < kSweeps; ++s) {
    Sweep& sweep = sweeps[static_cast<size_t>(s)];
    const Orientation& o = orientation[s < kColumnsRight ? 0 : 1];
    sweep.step = (s == kRowsUp || s == kColumnsRight) ? 1 : -1;
    sweep.first = sweep.step > 0 ? clamped_floor(o.slab_origin, o.slabs)
                                 : clamped_floor(std::ceil(o.slab_origin) - 1.0, o.slabs);
    sweep.reaching.assign(static_cast<size_t>(o.slabs) + 2, 0);
  }
  const int threads = num_threads();
  // counts[t][s][depth]: the rays of thread t's chunk in sweep s with that depth.
  counts.resize(static_cast<size_t>(threads));
  for (auto& per_thread : counts)
    for (int s = 0; s < kSweeps; ++s)
      per_thread[static_cast<size_t>(s)].assign(sweeps[static_cast<size_t>(s)].reaching.size(), 0);
  const auto n = static_cast<int64_t>(points.size());
  classes.resize(points.size());
  parallel_chunks(n, [&](int64_t begin, int64_t end, int t) {
    classify_rays(points.data(), begin, end, grid, orientation, classes.sweep.data(),
                  classes.depth.data(), classes.slope.data(), classes.first_cell.data(),
                  classes.last_cell.data(), classes.in_range.data());
    auto& mine = counts[static_cast<size_t>(t)];
    for (int64_t i = begin; i < end; ++i) {
      const uint8_t sweep = classes.sweep[static_cast<size_t>(i)];
      if (sweep < kSweeps)
        ++mine[sweep][static_cast<size_t>(classes.depth[static_cast<size_t>(i)])];
    }
  });
  // Places: the deepest rays first, and within one depth, thread chunks in order.
  for (int s = 0; s < kSweeps; ++s) {
    Sweep& sweep = sweeps[static_cast<size_t>(s)];
    const auto depths = static_cast<int64_t>(sweep.reaching.size());
    int64_t placed = 0;
    for (int64_t d = depths - 1; d >= 0; --d) {
      for (auto& per_thread : counts) {
        int64_t& slot = per_thread[static_cast<size_t>(s)][static_cast<size_t>(d)];
        const int64_t rays = slot;
        slot = placed;
        placed += rays;
      }
      sweep.reaching[static_cast<size_t>(d)] = placed;
    }
    sweep.resize(placed);
  }
  // Raw pointers in locals: the byte stores (in_range) may alias anything, so through the
  // vectors every store would make the compiler load every data pointer again.
  struct Arrays {
    double* slope;
    int32_t *first_cell, *last_cell;
    uint32_t* point;
    uint8_t* in_range;
  };
  std::array<Arrays, kSweeps> to{};
  for (int s = 0; s < kSweeps; ++s) {
    Sweep& sweep = sweeps[static_cast<size_t>(s)];
    to[static_cast<size_t>(s)] = {sweep.slope.data(), sweep.first_cell.data(),
                                  sweep.last_cell.data(), sweep.point.data(),
                                  sweep.in_range.data()};
  }
  parallel_chunks(n, [&](int64_t begin, int64_t end, int t) {
    std::array<int64_t*, kSweeps> next{};
    for (int s = 0; s < kSweeps; ++s)
      next[static_cast<size_t>(s)] = counts[static_cast<size_t>(t)][static_cast<size_t>(s)].data();
    const std::array<Arrays, kSweeps> sweep_arrays = to;
    const uint8_t* sweep_of = classes.sweep.data();
    const int32_t* depth = classes.depth.data();
    const double* slope = classes.slope.data();
    const int32_t* first_cell = classes.first_cell.data();
    const int32_t* last_cell = classes.last_cell.data();
    const uint8_t* in_range = classes.in_range.data();
    for (int64_t i = begin; i < end; ++i) {
      const uint8_t s = sweep_of[i];
      if (s == kSweeps) continue;
      const Arrays& out = sweep_arrays[s];
      const int64_t k = next[s][depth[i]]++;
      out.slope[k] = slope[i];
      out.first_cell[k] = first_cell[i];
      out.last_cell[k] = last_cell[i];
      out.point[k] = static_cast<uint32_t>(i);
      out.in_range[k] = in_range[i];
    }
  });
}

// Bands [bounds[t], bounds[t + 1]) of the indices of `work`, one per thread, each holding about
// the same share of the total work.
std::vector<int64_t> balanced_bands(const std::vector<int64_t>& work, int threads) {
  const auto n = static_cast<int64_t>(work.size());
  std::vector<int64_t> bounds(static_cast<size_t>(threads) + 1, n);
  bounds[0] = 0;
  int64_t total = 0;
  for (int64_t w : work) total += w;
  int64_t done = 0, i = 0;
  for (int t = 1; t < threads; ++t) {
    while (i < n && (done + work[static_cast<size_t>(i)]) * threads <= total * t)
      done += work[static_cast<size_t>(i++)];
    bounds[static_cast<size_t>(t)] = std::max(bounds[static_cast<size_t>(t) - 1], i);
  }
  return bounds;
}

// Per-thread buffers of a band's sweep. A ray's run in a slab goes from the cell where it enters
// the slab to the cell where it leaves it: both are crossings of slab boundaries ("events"), and
// the event where a ray leaves one slab is the one where it enters the next. So each ray costs
// one event per slab boundary, counted per cell and per direction of the run (towards higher
// cells, or not moving along the run axis: "rightwards"; else "leftwards"), and a slab's changes
// along the run axis follow from the events at its two boundaries: a rightwards run adds 1 at its
// entry cell and takes it back after its exit cell, a leftwards one adds 1 at its exit cell and
// takes it back after its entry cell. Rows are indexed by cell + 2: cells -1 .. cells + 1 after a
// slot that stays zero. Between calls every row is all zero (sweep_band clears what it used), so
// a scratch can be kept from one call to the next.
struct SweepScratch {
  static constexpr int64_t kCopies = 4;   // event rows per direction, so that consecutive rays'
                                          // counts never wait on one another's (rays often share
                                          // cells)
  static constexpr int64_t kChunk = 512;  // rays whose events are worked out together
  // Ready for a run axis of `cells` cells, keeping the memory where it can.
  void prepare(int64_t cells) {
    crossing.resize(static_cast<size_t>(kChunk));
    places.resize(static_cast<size_t>(kChunk));
    if (stride != cells + 4) {
      stride = cells + 4;
      copies.assign(static_cast<size_t>(2 * kCopies * stride), 0);
      entering.assign(static_cast<size_t>(2 * stride), 0);
      leaving.assign(static_cast<size_t>(2 * stride), 0);
      changes.assign(static_cast<size_t>(stride), 0);
      counts.resize(static_cast<size_t>(cells));
    }
  }
  std::vector<int32_t> crossing;   // the cells where a chunk's rays cross a boundary
  std::vector<int32_t> places;     // where in `copies` each of them is counted
  int64_t stride = 0;              // one row: cells + 4
  std::vector<uint32_t> copies;    // (2 directions x kCopies, stride): events being counted
  std::vector<uint32_t> entering;  // (2 directions, stride): events at the slab's entry boundary
  std::vector<uint32_t> leaving;   // (2 directions, stride): events at its exit boundary
  std::vector<int32_t> changes;    // (stride): the slab's changes along the run axis
  std::vector<uint32_t> counts;    // one slab's counts along the run axis
};

// out[k] = the run-axis cell where ray first_ray + k of the sweep crosses the slab boundary
// `boundary`, for k < rays: CrossingCell::at, in one pass in double that the compiler vectorises
// (as CrossingCell::fill), and the exact evaluation for the values that lie near a tie.
void crossings(const Sweep& sweep, const Orientation& o, double boundary, int64_t first_ray,
               int64_t rays, int32_t* out) {
  constexpr double kRoundToInteger = 0x1.8p52;
  const double offset = boundary - o.slab_origin, origin = o.run_origin, window = o.window;
  const double* slope = sweep.slope.data() + first_ray;
  const int32_t* first = sweep.first_cell.data() + first_ray;
  const int32_t* last = sweep.last_cell.data() + first_ray;
  int64_t near_ties = 0;
  for (int64_t k = 0; k < rays; ++k) {
    const double first_k = first[k], last_k = last[k];
    const double lo_k = std::min(first_k, last_k), hi_k = std::max(first_k, last_k);
    const double value =
        std::min(std::max(std::fma(offset, slope[k], origin), lo_k - 0.5), hi_k + 1.5);
    const double nearest = (value + kRoundToInteger) - kRoundToInteger;
    const double distance = value - nearest;
    near_ties += std::abs(distance) <= window;
    out[k] = static_cast<int32_t>(
        std::min(std::max(distance < 0.0 ? nearest - 1.0 : nearest, lo_k), hi_k));
  }
  if (near_ties == 0) return;
  for (int64_t k = 0; k < rays; ++k) {
    const double first_k = first[k], last_k = last[k];
    const double lo_k = std::min(first_k, last_k), hi_k = std::max(first_k, last_k);
    const double value =
        std::min(std::max(std::fma(offset, slope[k], origin), lo_k - 0.5), hi_k + 1.5);
    if (std::abs(value - std::nearbyint(value)) > window) continue;
    const Point& p = o.points[sweep.point[static_cast<size_t>(first_ray + k)]];
    const RayAxis along = make_axis(o.run_origin, o.run_end(p), o.cells);
    const RayAxis across = make_axis(o.slab_origin, o.slab_end(p), o.slabs);
    out[k] =
        static_cast<int32_t>(CrossingCell(along, across, o.run_steps_first, o.cells).at(boundary));
  }
}

// Counts the events of rays [0, rays) of the sweep at one boundary into the rows of `copies`
// (direction and copy), cells given by crossing[k] for ray first_ray + k; widens [lo, hi] (row
// indices) to the places counted.
void count_events(const Sweep& sweep, int64_t first_ray, int64_t rays, SweepScratch& scratch,
                  int64_t& lo, int64_t& hi) {
  const int32_t* crossing = scratch.crossing.data();
  int32_t* places = scratch.places.data();
  const int32_t* first = sweep.first_cell.data() + first_ray;
  const int32_t* last = sweep.last_cell.data() + first_ray;
  const auto stride = static_cast<int32_t>(scratch.stride);
  constexpr auto kCopies = static_cast<int32_t>(SweepScratch::kCopies);
  int32_t lowest = std::numeric_limits<int32_t>::max(), highest = -1;
  for (int64_t k = 0; k < rays; ++k) {
    const int32_t leftwards = last[k] < first[k];
    const int32_t row = leftwards * kCopies + static_cast<int32_t>(k & (kCopies - 1));
    const int32_t column = crossing[k] + 2;
    places[k] = row * stride + column;
    lowest = std::min(lowest, column);
    highest = std::max(highest, column);
  }
  uint32_t* copies = scratch.copies.data();
  for (int64_t k = 0; k < rays; ++k) ++copies[places[k]];
  if (rays > 0) {
    lo = std::min<int64_t>(lo, lowest);
    hi = std::max<int64_t>(hi, highest);
  }
}

// Sums the rows of `copies` over row indices [lo, hi] into target (2 directions, stride), which
// is zero there on entry, and clears them.
void gather_events(SweepScratch& scratch, int64_t lo, int64_t hi, uint32_t* target) {
  if (lo > hi) return;
  const int64_t stride = scratch.stride;
  for (int64_t direction = 0; direction < 2; ++direction) {
    uint32_t* sum = target + direction * stride;
    for (int64_t copy = 0; copy < SweepScratch::kCopies; ++copy) {
      uint32_t* row = scratch.copies.data() + (direction * SweepScratch::kCopies + copy) * stride;
      for (int64_t j = lo; j <= hi; ++j) sum[j] += row[j];
      std::fill(row + lo, row + hi + 1, 0u);
    }
  }
}

// Zeroes row indices [lo, hi] of both directions' rows of `events` (2 directions, stride).
void clear_events(uint32_t* events, int64_t stride, int64_t lo, int64_t hi) {
  if (lo > hi) return;
  std::fill(events + lo, events + hi + 1, 0u);
  std::fill(events + stride + lo, events + stride + hi + 1, 0u);
}

// Walks the sweep's rays through the slabs [slab_lo, slab_hi), in sweep order. For each slab
// some ray reaches, hands flush(slab, counts, from, to) the transmissions along the run axis made
// in that slab (counts[c] for c in [from, to); zero elsewhere), and calls detect(slab, cell) for
// each ray whose point lies in the grid there.
template <class Flush, class Detect>
void sweep_band(const Sweep& sweep, const Orientation& o, int64_t slab_lo, int64_t slab_hi,
                SweepScratch& scratch, Flush&& flush, Detect&& detect) {
  const int64_t s = sweep.step;
  const int64_t start = s > 0 ? std::max(slab_lo, sweep.first) : std::min(slab_hi - 1, sweep.first);
  const int64_t stop = s > 0 ? slab_hi : slab_lo - 1;  // one past the last slab, in sweep order
  if ((stop - start) * s <= 0) return;
  int64_t d = sweep.depth(start);
  if (sweep.reaching[static_cast<size_t>(d)] == 0) return;
  const int64_t cells = o.cells, stride = scratch.stride;
  const int32_t* first = sweep.first_cell.data();
  const int32_t* last = sweep.last_cell.data();
  uint32_t* entering = scratch.entering.data();
  uint32_t* leaving = scratch.leaving.data();
  int32_t* changes = scratch.changes.data();
  // The events where the rays enter the first slab: their cells along the run axis as they leave
  // the origin, or their crossings of its entry boundary; [entry_lo, entry_hi]: the row indices
  // holding them.
  int64_t entry_lo = stride, entry_hi = -1;
  const int64_t entering_rays = sweep.reaching[static_cast<size_t>(d)];
  for (int64_t chunk = 0; chunk < entering_rays; chunk += SweepScratch::kChunk) {
    const int64_t n = std::min(SweepScratch::kChunk, entering_rays - chunk);
    if (d == 0) {
      std::copy_n(first + chunk, n, scratch.crossing.data());
    } else {
      crossings(sweep, o, static_cast<double>(s > 0 ? start : start + 1), chunk, n,
                scratch.crossing.data());
    }
    count_events(sweep, chunk, n, scratch, entry_lo, entry_hi);
  }
  gather_events(scratch, entry_lo, entry_hi, entering);
  for (int64_t slab = start; slab != stop; slab += s, ++d) {
    const int64_t rays = sweep.reaching[static_cast<size_t>(d)];
    if (rays == 0) break;
    const int64_t continuing = sweep.reaching[static_cast<size_t>(d) + 1];
    const double exit = static_cast<double>(s > 0 ? slab + 1 : slab);
    // The events at the exit boundary, of the rays that go on.
    int64_t exit_lo = stride, exit_hi = -1;
    for (int64_t chunk = 0; chunk < continuing; chunk += SweepScratch::kChunk) {
      const int64_t n = std::min(SweepScratch::kChunk, continuing - chunk);
      crossings(sweep, o, exit, chunk, n, scratch.crossing.data());
      count_events(sweep, chunk, n, scratch, exit_lo, exit_hi);
    }
    gather_events(scratch, exit_lo, exit_hi, leaving);
    // Rightwards: +1 at the entry cell, -1 after the exit cell; leftwards: +1 at the exit cell,
    // -1 after the entry cell. [lo, hi]: the row indices where the changes may be non-zero.
    int64_t lo = std::min(entry_lo, exit_lo), hi = std::max(entry_hi, exit_hi) + 1;
    const uint32_t* entering_right = entering;
    const uint32_t* entering_left = entering + stride;
    const uint32_t* leaving_right = leaving;
    const uint32_t* leaving_left = leaving + stride;
    for (int64_t j = lo; j <= hi; ++j) {
      changes[j] += static_cast<int32_t>(entering_right[j] - leaving_right[j - 1] +
                                         leaving_left[j] - entering_left[j - 1]);
    }
    // The rays ending here: their run stops at their end cell, which counts a detection, not a
    // transmission.
    for (int64_t k = continuing; k < rays; ++k) {
      const int64_t end = last[k];
      const int64_t j = end + 2;
      if (end >= first[k]) {
        --changes[j + 1];
      } else {
        ++changes[j];
      }
      lo = std::min(lo, j), hi = std::max(hi, j + 1);
      if (end < 0 || end >= cells) continue;
      --changes[j];
      ++changes[j + 1];
      if (sweep.in_range[static_cast<size_t>(k)]) detect(slab, end);
    }
    // Counts: running sums of the changes (cell c at row index c + 2).
    uint32_t* counts = scratch.counts.data();
    int32_t running = 0;
    int64_t from = cells, to = 0;
    for (int64_t j = lo; j <= hi; ++j) {
      running += changes[j];
      changes[j] = 0;
      const int64_t c = j - 2;
      if (c >= 0 && c < cells) {
        counts[c] = static_cast<uint32_t>(running);
        from = std::min(from, c), to = c + 1;
      }
    }
    // The exit events become the next slab's entry events.
    clear_events(entering, stride, entry_lo, entry_hi);
    std::swap(entering, leaving);
    entry_lo = exit_lo, entry_hi = exit_hi;
    if (from < to) flush(slab, static_cast<const uint32_t*>(counts), from, to);
  }
  clear_events(entering, stride, entry_lo, entry_hi);
}

// Up to kWidth consecutive columns of counts, gathered a column at a time and added to the (H, W)
// output a row segment at a time; only columns [lo, hi) (the thread's band) are written.
class ColumnStrip {
 public:
  static constexpr int64_t kWidth = 16;
  ColumnStrip(uint32_t* out, int64_t width, int64_t height, int64_t lo, int64_t hi)
      : out_(out),
        width_(width),
        height_(height),
        lo_(lo),
        hi_(hi),
        strip_(static_cast<size_t>(height * kWidth), 0) {}
  ~ColumnStrip() = default;
  ColumnStrip(const ColumnStrip&) = delete;
  ColumnStrip& operator=(const ColumnStrip&) = delete;

  // counts[r] for rows r in [from, to), zero elsewhere.
  void put(int64_t column, const uint32_t* counts, int64_t from, int64_t to) {
    const int64_t begin = column - column % kWidth;
    if (begin != begin_) {
      flush();
      begin_ = begin;
    }
    const int64_t j = column - begin_;
    for (int64_t r = from; r < to; ++r) strip_[static_cast<size_t>(r * kWidth + j)] = counts[r];
  }

  // Adds the gathered columns to the output and clears the strip.
  void flush() {
    if (begin_ < 0) return;
    const int64_t from = std::max(begin_, lo_), to = std::min(begin_ + kWidth, hi_);
    for (int64_t r = 0; r < height_; ++r) {
      uint32_t* row = out_ + r * width_;
      const uint32_t* gathered = strip_.data() + r * kWidth - begin_;
      for (int64_t c = from; c < to; ++c) row[c] += gathered[c];
    }
    std::fill(strip_.begin(), strip_.end(), 0u);
    begin_ = -1;
  }

 private:
  uint32_t* out_;
  int64_t width_, height_, lo_, hi_;
  int64_t begin_ = -1;
  std::vector<uint32_t> strip_;  // (H, kWidth)
};

}  // namespace

// What ObservabilityWorkspace keeps between calls.
struct SweepBuffers {
  std::array<Sweep, kSweeps> sweeps;
  std::vector<std::array<std::vector<int64_t>, kSweeps>> counts;  // build_sweeps' per thread
  RayClasses classes;                                             // build_sweeps' per point
  std::array<std::vector<SweepScratch>, 2> scratch;               // per family, per band
};

void count_observability_2d(std::span<const Point> points, double origin_u, double origin_v,
                            const GridSpec& grid, SweepBuffers& buffers, uint32_t* transmissions,
                            uint32_t* detections) {
  const int64_t width = grid.width(), height = grid.height();
  const std::array<Orientation, 2> orientation = {
      Orientation{height, width, origin_v, origin_u, true,
                  CrossingCell::tie_window(width, origin_u), true, &grid, points.data()},
      Orientation{width, height, origin_u, origin_v, false,
                  CrossingCell::tie_window(height, origin_v), false, &grid, points.data()}};
  std::array<Sweep, kSweeps>& sweeps = buffers.sweeps;
  build_sweeps(points, grid, orientation, sweeps, buffers.counts, buffers.classes);
  const int threads = num_threads();
  for (int family = 0; family < 2; ++family) {
    const Orientation& o = orientation[static_cast<size_t>(family)];
    const Sweep& forward = sweeps[static_cast<size_t>(2 * family)];
    const Sweep& backward = sweeps[static_cast<size_t>(2 * family + 1)];
    std::vector<int64_t> work(static_cast<size_t>(o.slabs));
    for (int64_t slab = 0; slab < o.slabs; ++slab)
      work[static_cast<size_t>(slab)] = forward.reaching_slab(slab) + backward.reaching_slab(slab);
    const std::vector<int64_t> bands = balanced_bands(work, threads);
    std::vector<SweepScratch>& scratches = buffers.scratch[static_cast<size_t>(family)];
    if (scratches.size() < static_cast<size_t>(threads))
      scratches.resize(static_cast<size_t>(threads));
    parallel_chunks(threads, [&](int64_t begin, int64_t end, int) {
      for (int64_t band = begin; band < end; ++band) {
        const int64_t lo = bands[static_cast<size_t>(band)],
                      hi = bands[static_cast<size_t>(band) + 1];
        if (lo >= hi) continue;
        SweepScratch& scratch = scratches[static_cast<size_t>(band)];
        scratch.prepare(o.cells);
        if (family == 0) {
          const auto add_row = [&](int64_t row, const uint32_t* counts, int64_t from, int64_t to) {
            uint32_t* out = transmissions + row * width;
            for (int64_t c = from; c < to; ++c) out[c] += counts[c];
          };
          const auto detect = [&](int64_t row, int64_t column) {
            ++detections[row * width + column];
          };
          sweep_band(forward, o, lo, hi, scratch, add_row, detect);
          sweep_band(backward, o, lo, hi, scratch, add_row, detect);
        } else {
          const auto detect = [&](int64_t column, int64_t row) {
            ++detections[row * width + column];
          };
          for (const Sweep* sweep : {&forward, &backward}) {
            ColumnStrip strip(transmissions, width, height, lo, hi);
            sweep_band(
                *sweep, o, lo, hi, scratch,
                [&](int64_t column, const uint32_t* counts, int64_t from, int64_t to) {
                  strip.put(column, counts, from, to);
                },
                detect);
            strip.flush();
          }
        }
      }
    });
  }
}

}  // namespace pillarseg::host::raywalk_detail

namespace pillarseg::host {

ObservabilityWorkspace::ObservabilityWorkspace()
    : buffers_(std::make_unique<raywalk_detail::SweepBuffers>()) {}
ObservabilityWorkspace::~ObservabilityWorkspace() = default;
ObservabilityWorkspace::ObservabilityWorkspace(ObservabilityWorkspace&&) noexcept = default;
ObservabilityWorkspace& ObservabilityWorkspace::operator=(ObservabilityWorkspace&&) noexcept =
    default;

raywalk_detail::SweepBuffers& ObservabilityWorkspace::buffers() {
  if (!buffers_) buffers_ = std::make_unique<raywalk_detail::SweepBuffers>();
  return *buffers_;
}

}  // namespace pillarseg::host
