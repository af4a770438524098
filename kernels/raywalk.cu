// Ray walks (see raywalk.cuh), one thread per ray, on the walk of host/raywalk.cpp: the ray is cut
// into slabs across one axis (rows, or columns), its cells in each slab form one run along the
// other axis, from the cell where it crosses into the slab to the cell where it crosses out (in
// 3D a run splits where the ray crosses a layer boundary); the cell at each crossing is decided
// exactly (a double evaluation, and near a tie the exact sign of an orientation from error-free
// products and expansion sums). The device functions below are that code, line for line, so that
// both visit the same cells; only the expansion sum is laid out in fixed slots, to stay in
// registers (the same two-sums on the same components, see exact_sign_of_dot6). A run adds 1 to a
// difference array at its first cell and takes it after its last (two atomics whatever its length);
// runs along x go to the counts themselves, runs along y (2D rays that move more along y) to the
// workspace. Then, per line of the grid, a block turns the differences into counts with a prefix
// sum (the y differences first summed down the columns, one thread per column).
#include "kernels/raywalk.cuh"

#include <cmath>
#include <cstdint>
#include <limits>

#include "kernels/block_scan.cuh"
#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kRayThreads = 128;
constexpr int kLineThreads = 256;  // prefix sums along a line of W cells
constexpr int kColumnThreads = 256;
constexpr std::int64_t kMaxCellsPerAxis = std::int64_t{1} << 24;  // as the host

// The grid as the walk sees it: sizes, and the bounds GridSpec::contains tests.
struct WalkGrid {
  double x_min, x_max, y_min, y_max, z_min, z_max, cell, voxel_z;
  std::int64_t width, height, layers;  // layers = 1 for a 2D walk
};

// The origin in cell coordinates u, v, w.
struct OriginCells {
  double u, v, w;
};

}  // namespace

// ---- the walk (host/raywalk.cpp, in device code) ----

static __device__ __forceinline__ std::int64_t min64(std::int64_t a, std::int64_t b) {
  return b < a ? b : a;
}
static __device__ __forceinline__ std::int64_t max64(std::int64_t a, std::int64_t b) {
  return a < b ? b : a;
}

// floor(value) clamped to [-1, n]: -1 and n stand for every cell beyond the grid on that side.
static __device__ std::int64_t clamped_floor(double value, std::int64_t n) {
  if (!(value >= -1.0)) return -1;
  if (value >= static_cast<double>(n)) return n;
  return static_cast<std::int64_t>(floor(value));
}

namespace {

// One axis of a ray in cell coordinates, from `origin` (t = 0) to `end` (t = 1).
struct RayAxis {
  double origin, end;
  double delta;        // end - origin, rounded
  int step;            // sign of end - origin
  std::int64_t first;  // the cell the ray enters from the origin, clamped to [-1, n]
  std::int64_t last;   // floor(end), clamped to [-1, n]

  __device__ std::int64_t lo() const { return min64(first, last); }
  __device__ std::int64_t hi() const { return max64(first, last); }
};

}  // namespace

static __device__ RayAxis make_axis(double origin, double end, std::int64_t n) {
  RayAxis axis;
  axis.origin = origin;
  axis.end = end;
  axis.delta = end - origin;
  axis.step = (end > origin) - (end < origin);
  axis.first = axis.step < 0 ? clamped_floor(ceil(origin) - 1.0, n) : clamped_floor(origin, n);
  axis.last = clamped_floor(end, n);
  return axis;
}

// sum + err == a + b exactly (Knuth's two-sum).
static __device__ __forceinline__ void two_sum(double a, double b, double& sum, double& err) {
  sum = a + b;
  const double b_virtual = sum - a;
  const double a_virtual = sum - b_virtual;
  err = (a - a_virtual) + (b - b_virtual);
}

// x * y rounded to double, never contracted with a later add into an fma: the expansion below
// needs the product as rounded, whose error the fma beside it computes.
static __device__ __forceinline__ double rounded_product(double x, double y) {
#if defined(__CUDA_ARCH__)
  return __dmul_rn(x, y);
#else
  return x * y;
#endif
}

// The exact sign of sum_i x[i] * y[i] over 6 terms, as the host's exact_sign_of_dot: products
// split by fma into value and error, accumulated into a nonoverlapping expansion (Shewchuk's
// Grow-Expansion with zero elimination). Here the expansion keeps one slot per grow (grow g
// fills slot g): a component the host eliminates stays as a zero in its slot and later grows
// skip it, so the nonzero slots, in order, are the host's expansion, built by the same two-sums.
// Unrolled, every slot index is a constant and the expansion lives in registers, not in local
// memory.
static __device__ __forceinline__ int exact_sign_of_dot6(const double (&x)[6],
                                                         const double (&y)[6]) {
  constexpr int kSlots = 12;
  double slot[kSlots];
#pragma unroll
  for (int g = 0; g < kSlots; ++g) {
    const double product = rounded_product(x[g / 2], y[g / 2]);
    double running = g % 2 == 0 ? fma(x[g / 2], y[g / 2], -product) : product;
#pragma unroll
    for (int i = 0; i < g; ++i) {
      if (slot[i] == 0.0) continue;
      double sum = 0.0, err = 0.0;
      two_sum(running, slot[i], sum, err);
      slot[i] = err;
      running = sum;
    }
    slot[g] = running;
  }
  // The sign of the largest component: the last nonzero slot, searched from the top (GCC 12.2's
  // vectorizer miscompiles the forward "last nonzero wins" loop, and the emulation builds this).
#pragma unroll
  for (int i = kSlots - 1; i >= 0; --i) {
    if (slot[i] != 0.0) return slot[i] > 0.0 ? 1 : -1;
  }
  return 0;
}

namespace {

// The cell along axis m where the ray crosses a cell boundary of axis a, clamped to
// [m.lo(), m.hi()]; at a simultaneous m-crossing, m_steps_first says which axis steps first.
struct CrossingCell {
  RayAxis m, a;
  bool m_steps_first;
  std::int64_t lo, hi;
  double slope, window;

  __device__ CrossingCell(const RayAxis& m_axis, const RayAxis& a_axis, bool steps_first,
                          std::int64_t m_cells)
      : m(m_axis), a(a_axis), m_steps_first(steps_first), lo(m_axis.lo()), hi(m_axis.hi()) {
    slope = a.delta != 0.0 ? m.delta / a.delta : 0.0;
    window = 0x1p-30 * (static_cast<double>(m_cells) + 2.0 + fabs(m.origin));
  }

  // boundary: the a-coordinate of the crossed boundary (an integer).
  __device__ std::int64_t at(double boundary) const {
    if (m.step == 0) return m.first;
    const double value = fma(boundary - a.origin, slope, m.origin);
    if (!(value > static_cast<double>(lo))) return lo;
    if (!(value < static_cast<double>(hi + 1))) return hi;
    const double nearest = rint(value);
    const std::int64_t cell = fabs(value - nearest) > window
                                  ? static_cast<std::int64_t>(floor(value))
                                  : exact_cell(boundary, nearest);
    return min64(max64(cell, lo), hi);
  }

  // The cell beside the integer k, from the exact sign of (m(t) - k) (a.end - a.origin).
  __device__ std::int64_t exact_cell(double boundary, double k) const {
    const double x[6] = {m.origin, -k, k, boundary, -boundary, -a.origin};
    const double y[6] = {a.end, a.end, a.origin, m.end, m.origin, m.end};
    const int side = a.step * exact_sign_of_dot6(x, y);
    const auto cell = static_cast<std::int64_t>(k);
    if (side > 0) return cell;
    if (side < 0) return cell - 1;
    return m_steps_first == (m.step > 0) ? cell : cell - 1;
  }
};

}  // namespace

// Narrows [t0, t1] to where the ray lies within one cell of the cells [0, n) of this axis.
static __device__ void clip_to_cells(const RayAxis& axis, std::int64_t n, double& t0, double& t1) {
  if (axis.lo() >= 0 && axis.hi() < n) return;
  if (axis.step == 0) {
    t1 = -1.0;
    return;
  }
  const double inverse = 1.0 / axis.delta;
  double ta = (-1.0 - axis.origin) * inverse;
  double tb = (static_cast<double>(n + 1) - axis.origin) * inverse;
  if (ta > tb) {
    const double swap = ta;
    ta = tb;
    tb = swap;
  }
  t0 = t0 < ta ? ta : t0;
  t1 = tb < t1 ? tb : t1;
}

// The coordinate of the boundary crossed when leaving cell c with `step`, or entering it.
static __device__ __forceinline__ double exit_boundary(std::int64_t c, std::int64_t step) {
  return static_cast<double>(step > 0 ? c + 1 : c);
}
static __device__ __forceinline__ double entry_boundary(std::int64_t c, std::int64_t step) {
  return exit_boundary(c - step, step);
}

// Calls run(slab, layer, from, to) for the runs of the walk of (u, v, w) within the grid's slabs,
// in walk order; slabs are rows (kRunsAlongX, runs along x) or columns (runs along y). Runs are
// not cut to the grid along the run axis nor in z: run() cuts them.
template <bool kRunsAlongX, bool kThreeD, class Run>
static __device__ void walk_runs(const RayAxis& u, const RayAxis& v, const RayAxis& w,
                                 const WalkGrid& grid, Run&& run) {
  double t0 = 0.0, t1 = 1.0;
  clip_to_cells(u, grid.width, t0, t1);
  clip_to_cells(v, grid.height, t0, t1);
  if constexpr (kThreeD) clip_to_cells(w, grid.layers, t0, t1);
  if (t0 > t1) return;
  const RayAxis& across = kRunsAlongX ? v : u;
  const RayAxis& along = kRunsAlongX ? u : v;
  const std::int64_t across_cells = kRunsAlongX ? grid.height : grid.width;
  const std::int64_t along_cells = kRunsAlongX ? grid.width : grid.height;
  const double at_t0 = across.origin + t0 * across.delta;
  const double at_t1 = across.origin + t1 * across.delta;
  const std::int64_t lo =
      max64(max64(clamped_floor(at_t0 < at_t1 ? at_t0 : at_t1, across_cells) - 1, across.lo()), 0);
  const std::int64_t hi =
      min64(min64(clamped_floor(at_t0 < at_t1 ? at_t1 : at_t0, across_cells) + 1, across.hi()),
            across_cells - 1);
  if (lo > hi) return;
  const std::int64_t step = across.step >= 0 ? 1 : -1;
  const std::int64_t first = step > 0 ? lo : hi, slabs = hi - lo + 1;
  const bool starts_here = first == across.first;
  const bool ends_here = (step > 0 ? hi : lo) == across.last;
  const CrossingCell along_at_slab(along, across, kRunsAlongX, along_cells);
  std::int64_t cell = starts_here ? along.first : along_at_slab.at(entry_boundary(first, step));
  if constexpr (!kThreeD) {
    for (std::int64_t i = 0; i < slabs; ++i) {
      const std::int64_t slab = first + i * step;
      const std::int64_t cell_out =
          ends_here && i == slabs - 1 ? along.last : along_at_slab.at(exit_boundary(slab, step));
      run(slab, std::int64_t{0}, cell, cell_out);
      cell = cell_out;
    }
  } else {
    const CrossingCell layer_at_slab(w, across, false, grid.layers);
    const CrossingCell along_at_layer(along, w, true, along_cells);
    std::int64_t layer = starts_here ? w.first : layer_at_slab.at(entry_boundary(first, step));
    for (std::int64_t i = 0; i < slabs; ++i) {
      const std::int64_t slab = first + i * step;
      const bool last_slab = ends_here && i == slabs - 1;
      const std::int64_t cell_out =
          last_slab ? along.last : along_at_slab.at(exit_boundary(slab, step));
      const std::int64_t layer_out =
          last_slab ? w.last : layer_at_slab.at(exit_boundary(slab, step));
      for (; (layer_out - layer) * w.step > 0; layer += w.step) {
        const std::int64_t cell_at = along_at_layer.at(exit_boundary(layer, w.step));
        run(slab, layer, cell, cell_at);
        cell = cell_at;
      }
      run(slab, layer, cell, cell_out);
      cell = cell_out;
    }
  }
}

// ---- counting ----

// Adds `weight` to the cells from..to of row `row` of layer `layer` (cut to the grid) as
// differences along x.
static __device__ __forceinline__ void add_along_x(std::uint32_t* along_x, const WalkGrid& grid,
                                                   std::int64_t row, std::int64_t layer,
                                                   std::int64_t from, std::int64_t to,
                                                   std::uint32_t weight) {
  const std::int64_t lo = max64(min64(from, to), 0);
  const std::int64_t hi = min64(max64(from, to), grid.width - 1);
  if (lo > hi || layer < 0 || layer >= grid.layers) return;
  std::uint32_t* line = along_x + (layer * grid.height + row) * grid.width;
  atomicAdd(line + lo, weight);
  if (hi + 1 < grid.width) atomicAdd(line + hi + 1, 0u - weight);
}

// Adds 1 to the cells from..to of column `column` (cut to the grid) as differences along y.
static __device__ __forceinline__ void add_along_y(std::uint32_t* along_y, const WalkGrid& grid,
                                                   std::int64_t column, std::int64_t from,
                                                   std::int64_t to) {
  const std::int64_t lo = max64(min64(from, to), 0);
  const std::int64_t hi = min64(max64(from, to), grid.height - 1);
  if (lo > hi) return;
  atomicAdd(along_y + lo * grid.width + column, 1u);
  if (hi + 1 < grid.height) atomicAdd(along_y + (hi + 1) * grid.width + column, 0xffffffffu);
}

// One thread per point: walks its ray. passed (Z, H, W) gets the differences along x of every
// cell of the walk but the end cell, along_y (H, W; 2D only) those of runs along y; ended gets
// +1 at the end cell when the point lies inside the grid.
template <bool kThreeD>
static __global__ void __launch_bounds__(kRayThreads)
    walk_rays_kernel(const float* __restrict__ points, std::int64_t num_points, OriginCells origin,
                     WalkGrid grid, std::uint32_t* __restrict__ passed,
                     std::uint32_t* __restrict__ along_y, std::uint32_t* __restrict__ ended) {
  const std::int64_t i = std::int64_t{blockIdx.x} * kRayThreads + threadIdx.x;
  if (i >= num_points) return;
  const float px = points[4 * i], py = points[4 * i + 1], pz = points[4 * i + 2];
  // x - x is NaN exactly for Inf and NaN: the host skips rays to non-finite points.
  if (!(px - px == 0.0f && py - py == 0.0f && pz - pz == 0.0f)) return;
  const double pu = (px - grid.x_min) / grid.cell;
  const double pv = (py - grid.y_min) / grid.cell;
  const RayAxis v = make_axis(origin.v, pv, grid.height);
  if (v.hi() < 0 || v.lo() >= grid.height) return;
  const RayAxis u = make_axis(origin.u, pu, grid.width);
  const RayAxis w = kThreeD ? make_axis(origin.w, (pz - grid.z_min) / grid.voxel_z, grid.layers)
                            : make_axis(0.5, 0.5, 1);
  if (kThreeD || fabs(u.delta) >= fabs(v.delta)) {
    walk_runs<true, kThreeD>(
        u, v, w, grid,
        [&](std::int64_t row, std::int64_t layer, std::int64_t from, std::int64_t to) {
          add_along_x(passed, grid, row, layer, from, to, 1u);
        });
  } else {
    walk_runs<false, kThreeD>(
        u, v, w, grid, [&](std::int64_t column, std::int64_t, std::int64_t from, std::int64_t to) {
          add_along_y(along_y, grid, column, from, to);
        });
  }
  // The walk's last cell is the end cell: a detection (hit), not a transmission (pass).
  const bool end_in_grid = u.last >= 0 && u.last < grid.width && v.last >= 0 &&
                           v.last < grid.height && w.last >= 0 && w.last < grid.layers;
  if (!end_in_grid) return;
  add_along_x(passed, grid, v.last, w.last, u.last, u.last, 0xffffffffu);
  const bool inside_xy = px >= grid.x_min && px < grid.x_max && py >= grid.y_min && py < grid.y_max;
  const bool inside = inside_xy && (!kThreeD || (pz >= grid.z_min && pz < grid.z_max));
  if (inside) atomicAdd(ended + (w.last * grid.height + v.last) * grid.width + u.last, 1u);
}

// along_y (H, W): differences down each column -> their prefix sums, one thread per column.
static __global__ void __launch_bounds__(kColumnThreads)
    column_prefix_kernel(std::uint32_t* __restrict__ along_y, std::int64_t height,
                         std::int64_t width) {
  const std::int64_t column = std::int64_t{blockIdx.x} * kColumnThreads + threadIdx.x;
  if (column >= width) return;
  std::uint32_t running = 0;
  for (std::int64_t row = 0; row < height; ++row) {
    std::uint32_t& value = along_y[row * width + column];
    running += value;
    value = running;
  }
}

// One block per line (layer, row) of W cells: counts = prefix sum of the line's differences
// along x, plus (2D) the line of column sums along_y.
static __global__ void __launch_bounds__(kLineThreads)
    line_prefix_kernel(std::uint32_t* __restrict__ along_x,
                       const std::uint32_t* __restrict__ along_y, std::int64_t width,
                       std::int64_t height) {
  const std::int64_t line = blockIdx.x;
  std::uint32_t* counts = along_x + line * width;
  const std::uint32_t* from_y = along_y != nullptr ? along_y + line % height * width : nullptr;
  std::uint32_t carry = 0;
  for (std::int64_t base = 0; base < width; base += kLineThreads) {
    const std::int64_t c = base + threadIdx.x;
    const std::uint32_t difference = c < width ? counts[c] : 0u;
    std::uint32_t chunk_total = 0;
    const std::uint32_t before = block_exclusive_scan<kLineThreads>(difference, &chunk_total);
    if (c < width) {
      counts[c] = carry + before + difference + (from_y != nullptr ? from_y[c] : 0u);
    }
    carry += chunk_total;
  }
}

static __global__ void __launch_bounds__(kLineThreads)
    observability_map_kernel(const std::uint32_t* __restrict__ transmissions,
                             const std::uint32_t* __restrict__ detections, std::int64_t n,
                             std::uint32_t* __restrict__ map) {
  const std::int64_t i = std::int64_t{blockIdx.x} * kLineThreads + threadIdx.x;
  if (i < n) map[i] = transmissions[i] + detections[i];
}

static __global__ void __launch_bounds__(kLineThreads)
    occupancy_probability_kernel(const std::uint32_t* __restrict__ hits,
                                 const std::uint32_t* __restrict__ passes, std::int64_t n,
                                 double log_odds_hit, double log_odds_pass,
                                 float* __restrict__ probability) {
  const std::int64_t i = std::int64_t{blockIdx.x} * kLineThreads + threadIdx.x;
  if (i >= n) return;
  const std::uint32_t h = hits[i], p = passes[i];
  if (h == 0 && p == 0) {
    probability[i] = 0.5f;
    return;
  }
  const double log_odds = h * log_odds_hit + p * log_odds_pass;
  probability[i] = static_cast<float>(1.0 / (1.0 + exp(-log_odds)));
}

// ---- launchers ----
namespace {

void check_grid(const GridSpec& grid, bool with_layers, const char* op) {
  PS_CHECK(std::isfinite(grid.cell) && grid.cell > 0.0,
           "{}: the grid cell must be a positive size, given {}", op, grid.cell);
  PS_CHECK(std::isfinite(grid.x_min) && std::isfinite(grid.y_min) && std::isfinite(grid.z_min),
           "{}: the grid minimum must be finite, given ({}, {}, {})", op, grid.x_min, grid.y_min,
           grid.z_min);
  PS_CHECK(grid.width() >= 1 && grid.width() <= kMaxCellsPerAxis && grid.height() >= 1 &&
               grid.height() <= kMaxCellsPerAxis,
           "{}: the grid must have 1 to {} cells per axis, given W = {}, H = {}", op,
           kMaxCellsPerAxis, grid.width(), grid.height());
  if (with_layers) {
    PS_CHECK(std::isfinite(grid.voxel_z) && grid.voxel_z > 0.0,
             "{}: the grid voxel_z must be a positive size, given {}", op, grid.voxel_z);
    PS_CHECK(grid.layers() >= 1 && grid.layers() <= kMaxCellsPerAxis,
             "{}: the grid must have 1 to {} layers, given Z = {}", op, kMaxCellsPerAxis,
             grid.layers());
    PS_CHECK(std::int64_t{grid.layers()} * grid.height() <= std::numeric_limits<int>::max(),
             "{}: Z H = {} x {} lines exceed the launch grid", op, grid.layers(), grid.height());
  }
}

void check_rays(const float* points, std::int64_t num_points, const SensorOrigin& origin,
                const char* op) {
  PS_CHECK(std::isfinite(origin.x) && std::isfinite(origin.y) && std::isfinite(origin.z),
           "{}: the sensor origin must be finite, given ({}, {}, {})", op, origin.x, origin.y,
           origin.z);
  PS_CHECK(num_points >= 0 && num_points <= std::numeric_limits<std::uint32_t>::max(),
           "{}: 0 to {} points fit the uint32 counts, given {}", op,
           std::numeric_limits<std::uint32_t>::max(), num_points);
  PS_CHECK(num_points == 0 || points != nullptr,
           "{}: points must point to {} floats (M x 4) of device memory", op, 4 * num_points);
}

WalkGrid walk_grid(const GridSpec& grid, bool with_layers) {
  return WalkGrid{grid.x_min,
                  grid.x_max,
                  grid.y_min,
                  grid.y_max,
                  grid.z_min,
                  grid.z_max,
                  grid.cell,
                  grid.voxel_z,
                  grid.width(),
                  grid.height(),
                  with_layers ? grid.layers() : 1};
}

// The origin in cell coordinates, as host/raywalk.cpp computes them (w only for 3D walks).
OriginCells origin_cells(const SensorOrigin& origin, const GridSpec& grid, bool with_w) {
  return {(origin.x - grid.x_min) / grid.cell, (origin.y - grid.y_min) / grid.cell,
          with_w ? (origin.z - grid.z_min) / grid.voxel_z : 0.0};
}

unsigned blocks_for(std::int64_t threads, int block_size) {
  return static_cast<unsigned>(ceil_div(threads, std::int64_t{block_size}));
}

}  // namespace

std::int64_t observability_2d_workspace_size(const GridSpec& grid) {
  check_grid(grid, false, "observability_2d_workspace_size");
  return grid.cells();
}

void observability_2d(const float* points, std::int64_t num_points, const SensorOrigin& origin,
                      const GridSpec& grid, std::uint32_t* transmissions, std::uint32_t* detections,
                      std::uint32_t* workspace, std::int64_t workspace_size, cudaStream_t stream) {
  constexpr const char* kOp = "observability_2d";
  check_grid(grid, false, kOp);
  check_rays(points, num_points, origin, kOp);
  const std::int64_t cells = grid.cells();
  PS_CHECK(transmissions != nullptr && detections != nullptr,
           "{}: transmissions and detections must each point to H W = {} uint32 of device memory",
           kOp, cells);
  PS_CHECK(workspace != nullptr && workspace_size >= cells,
           "{}: the workspace must hold observability_2d_workspace_size(grid) = {} uint32, given "
           "{} at {}",
           kOp, cells, workspace_size, static_cast<const void*>(workspace));
  const auto bytes = static_cast<std::size_t>(cells) * sizeof(std::uint32_t);
  PS_CUDA_CHECK(cudaMemsetAsync(transmissions, 0, bytes, stream));
  PS_CUDA_CHECK(cudaMemsetAsync(detections, 0, bytes, stream));
  PS_CUDA_CHECK(cudaMemsetAsync(workspace, 0, bytes, stream));
  const WalkGrid walk = walk_grid(grid, false);
  if (num_points > 0) {
    launch_kernel(walk_rays_kernel<false>, dim3(blocks_for(num_points, kRayThreads)),
                  dim3(kRayThreads), 0, stream, points, num_points,
                  origin_cells(origin, grid, false), walk, transmissions, workspace, detections);
  }
  launch_kernel(column_prefix_kernel, dim3(blocks_for(walk.width, kColumnThreads)),
                dim3(kColumnThreads), 0, stream, workspace, walk.height, walk.width);
  launch_kernel(line_prefix_kernel, dim3(static_cast<unsigned>(walk.height)), dim3(kLineThreads), 0,
                stream, transmissions, static_cast<const std::uint32_t*>(workspace), walk.width,
                walk.height);
}

void observability_map(const std::uint32_t* transmissions, const std::uint32_t* detections,
                       std::int64_t n, std::uint32_t* map, cudaStream_t stream) {
  PS_CHECK(n >= 0, "observability_map: expected n >= 0 cells, given {}", n);
  if (n == 0) return;
  PS_CHECK(transmissions != nullptr && detections != nullptr && map != nullptr,
           "observability_map: transmissions, detections and map must each point to {} uint32 of "
           "device memory",
           n);
  launch_kernel(observability_map_kernel, dim3(blocks_for(n, kLineThreads)), dim3(kLineThreads), 0,
                stream, transmissions, detections, n, map);
}

void occupancy_counts_3d(const float* points, std::int64_t num_points, const SensorOrigin& origin,
                         const GridSpec& grid, std::uint32_t* hits, std::uint32_t* passes,
                         cudaStream_t stream) {
  constexpr const char* kOp = "occupancy_counts_3d";
  check_grid(grid, true, kOp);
  check_rays(points, num_points, origin, kOp);
  const WalkGrid walk = walk_grid(grid, true);
  const std::int64_t voxels = walk.layers * walk.height * walk.width;
  PS_CHECK(hits != nullptr && passes != nullptr,
           "{}: hits and passes must each point to Z H W = {} uint32 of device memory", kOp,
           voxels);
  const auto bytes = static_cast<std::size_t>(voxels) * sizeof(std::uint32_t);
  PS_CUDA_CHECK(cudaMemsetAsync(hits, 0, bytes, stream));
  PS_CUDA_CHECK(cudaMemsetAsync(passes, 0, bytes, stream));
  if (num_points > 0) {
    launch_kernel(walk_rays_kernel<true>, dim3(blocks_for(num_points, kRayThreads)),
                  dim3(kRayThreads), 0, stream, points, num_points,
                  origin_cells(origin, grid, true), walk, passes,
                  static_cast<std::uint32_t*>(nullptr), hits);
  }
  launch_kernel(line_prefix_kernel, dim3(static_cast<unsigned>(walk.layers * walk.height)),
                dim3(kLineThreads), 0, stream, passes, static_cast<const std::uint32_t*>(nullptr),
                walk.width, walk.height);
}

void occupancy_probability(const std::uint32_t* hits, const std::uint32_t* passes, std::int64_t n,
                           float* probability, cudaStream_t stream) {
  PS_CHECK(n >= 0, "occupancy_probability: expected n >= 0 voxels, given {}", n);
  if (n == 0) return;
  PS_CHECK(hits != nullptr && passes != nullptr && probability != nullptr,
           "occupancy_probability: hits, passes and probability must each point to {} elements "
           "of device memory",
           n);
  launch_kernel(occupancy_probability_kernel, dim3(blocks_for(n, kLineThreads)), dim3(kLineThreads),
                0, stream, hits, passes, n, std::log(0.7 / 0.3), std::log(0.4 / 0.6), probability);
}

}  // namespace pillarseg::cuda
