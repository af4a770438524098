// Pillar gather: points (M, 4) -> pillars (see pillar_gather.cuh), in ten steps that each either
// give every output one writer or combine with integer atomics whose result does not depend on
// their order:
//   [cells]   one thread per point: its flat cell iy W + ix (-1 outside the volume), and
//             atomicMin of the point's index into first_point[cell]: the cell's first point;
//   [firsts]  flag = "this point is its cell's first point";
//   [scan]    exclusive prefix sum of the flags: the pillar id of each first point, i.e. pillars
//             numbered in order of first appearance; the total is n, the non-empty pillars;
//   [number]  pillar_of_cell[cell] = id and pillar_cell[id] = cell, from the first points;
//   [assign]  each point's pillar, and atomicAdd of 1 into size[pillar];
//   [scan]    pillar_begin = exclusive prefix sum of the sizes (CSR offsets);
//   [place]   each point into its pillar's segment of `members` at an atomicAdd cursor: the
//             segment holds the pillar's points in an order the scheduler chose;
//   [rank]    each point's rank in its pillar = how many points of the segment have a smaller
//             index; sorted[begin + rank] = the point: the segment in input order, whatever the
//             placement order was (a stable sort by pillar). The cost is the sum over pillars of
//             size^2 comparisons: small for real scans (pillars of tens to a few hundred points),
//             quadratic only when most of a scan falls into one 0.1 m cell;
//   [output]  one thread per (row, slot): the kept pillar and point of the host's selection.
// Device-wide prefix sums are three kernels: per-tile sums, one block scanning the tile sums,
// per-tile scans plus the tile's offset (kernels/block_scan.cuh).
#include "kernels/pillar_gather.cuh"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

#include "kernels/block_reduce.cuh"
#include "kernels/block_scan.cuh"
#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kPointThreads = 256;  // per-point and per-output kernels
constexpr int kScanTile = 1024;     // prefix sums: one element per thread

// The cropped volume as GridSpec::contains tests it, in double.
struct Volume {
  double x_min, x_max, y_min, y_max, z_min, z_max, cell;
  int width, height;
};

// The workspace, carved in this order from the caller's int32 buffer.
struct Workspace {
  std::uint32_t* first_point;    // (W H): smallest index of a point in the cell; 0xffffffff
                                 // (the memset's bytes 0xff) for an empty cell
  std::int32_t* pillar_of_cell;  // (W H): written for non-empty cells only
  std::int32_t* point_pillar;    // (M): the point's flat cell, then its pillar; -1 outside
  std::int32_t* first_flags;     // (M): 1 for a cell's first point, then the exclusive scan
  std::int32_t* members;         // (M): points grouped by pillar, in placement order
  std::int32_t* sorted;          // (M): points grouped by pillar, in input order
  std::int32_t* pillar_size;     // (Rn): points of pillar p, Rn = min(M, W H)
  std::int32_t* pillar_begin;    // (Rn): exclusive scan of pillar_size
  std::int32_t* pillar_cursor;   // (Rn): placement cursor
  std::int32_t* pillar_cell;     // (Rn): flat cell of pillar p
  std::int32_t* tile_sums;       // (ceil(M / kScanTile)): the prefix sums' per-tile totals
  std::int32_t* totals;          // (2): n (non-empty pillars), points inside
};

std::int64_t max_nonempty(std::int64_t num_points, std::int64_t cells) {
  return std::min(num_points, cells);
}

Workspace carve(std::int32_t* base, std::int64_t num_points, std::int64_t cells) {
  const std::int64_t rn = max_nonempty(num_points, cells);
  Workspace w{};
  std::int32_t* next = base;
  const auto take = [&next](std::int64_t count) {
    std::int32_t* start = next;
    next += count;
    return start;
  };
  w.first_point = reinterpret_cast<std::uint32_t*>(take(cells));
  w.pillar_of_cell = take(cells);
  w.point_pillar = take(num_points);
  w.first_flags = take(num_points);
  w.members = take(num_points);
  w.sorted = take(num_points);
  w.pillar_size = take(rn);
  w.pillar_begin = take(rn);
  w.pillar_cursor = take(rn);
  w.pillar_cell = take(rn);
  w.tile_sums = take(ceil_div(num_points, std::int64_t{kScanTile}));
  w.totals = take(2);
  return w;
}

std::int64_t workspace_size(std::int64_t num_points, std::int64_t cells) {
  return 2 * cells + 4 * num_points + 4 * max_nonempty(num_points, cells) +
         ceil_div(num_points, std::int64_t{kScanTile}) + 2;
}

unsigned blocks_for(std::int64_t threads, int block_size) {
  return static_cast<unsigned>(ceil_div(threads, std::int64_t{block_size}));
}

}  // namespace

// ---- device-wide exclusive prefix sum of int32 ----

// in (n) -> tile_sums[b] = sum of tile b.
static __global__ void __launch_bounds__(kScanTile)
    scan_tile_sums_kernel(const std::int32_t* __restrict__ in, std::int64_t n,
                          std::int32_t* __restrict__ tile_sums) {
  const std::int64_t i = std::int64_t{blockIdx.x} * kScanTile + threadIdx.x;
  const std::int32_t sum = block_sum<kScanTile>(i < n ? in[i] : 0);
  if (threadIdx.x == 0) tile_sums[blockIdx.x] = sum;
}

// tile_sums (tiles) -> their exclusive prefix sums, in place; *total = the sum of all. One block.
static __global__ void __launch_bounds__(kScanTile)
    scan_tile_offsets_kernel(std::int32_t* __restrict__ tile_sums, std::int64_t tiles,
                             std::int32_t* __restrict__ total) {
  std::int32_t carry = 0;
  for (std::int64_t base = 0; base < tiles; base += kScanTile) {
    const std::int64_t i = base + threadIdx.x;
    std::int32_t chunk_total = 0;
    const std::int32_t before =
        block_exclusive_scan<kScanTile>(i < tiles ? tile_sums[i] : 0, &chunk_total);
    if (i < tiles) tile_sums[i] = carry + before;
    carry += chunk_total;
  }
  if (threadIdx.x == 0) *total = carry;
}

// in (n) -> out (n) = exclusive prefix sums (out may be in). Each element is read, then written,
// by the same thread.
static __global__ void __launch_bounds__(kScanTile)
    scan_apply_kernel(const std::int32_t* in, std::int64_t n,
                      const std::int32_t* __restrict__ tile_offsets, std::int32_t* out) {
  const std::int64_t i = std::int64_t{blockIdx.x} * kScanTile + threadIdx.x;
  std::int32_t tile_total = 0;
  const std::int32_t before = block_exclusive_scan<kScanTile>(i < n ? in[i] : 0, &tile_total);
  if (i < n) out[i] = tile_offsets[blockIdx.x] + before;
}

namespace {

// out = exclusive prefix sums of in (n elements, n < 2^31), *total = their sum.
void exclusive_scan(const std::int32_t* in, std::int64_t n, std::int32_t* tile_sums,
                    std::int32_t* out, std::int32_t* total, cudaStream_t stream) {
  if (n == 0) {
    PS_CUDA_CHECK(cudaMemsetAsync(total, 0, sizeof(std::int32_t), stream));
    return;
  }
  const std::int64_t tiles = ceil_div(n, std::int64_t{kScanTile});
  launch_kernel(scan_tile_sums_kernel, dim3(static_cast<unsigned>(tiles)), dim3(kScanTile), 0,
                stream, in, n, tile_sums);
  launch_kernel(scan_tile_offsets_kernel, dim3(1), dim3(kScanTile), 0, stream, tile_sums, tiles,
                total);
  launch_kernel(scan_apply_kernel, dim3(static_cast<unsigned>(tiles)), dim3(kScanTile), 0, stream,
                in, n, tile_sums, out);
}

}  // namespace

// ---- the gather ----

// points (M, 4) -> point_pillar[i] = flat cell or -1; first_point[cell] = min index.
static __global__ void __launch_bounds__(kPointThreads)
    cells_kernel(const float* __restrict__ points, std::int64_t num_points, Volume volume,
                 std::int32_t* __restrict__ point_cell, std::uint32_t* __restrict__ first_point) {
  const std::int64_t i = std::int64_t{blockIdx.x} * kPointThreads + threadIdx.x;
  if (i >= num_points) return;
  const double x = points[4 * i], y = points[4 * i + 1], z = points[4 * i + 2];
  const float r = points[4 * i + 3];
  const double fx = floor((x - volume.x_min) / volume.cell);
  const double fy = floor((y - volume.y_min) / volume.cell);
  // As the host: a NaN, infinite or absurd reflectance leaves the point out (65504:
  // kMaxAbsReflectance of core/point.hpp).
  const bool inside = x >= volume.x_min && x < volume.x_max && y >= volume.y_min &&
                      y < volume.y_max && z >= volume.z_min && z < volume.z_max && fx >= 0.0 &&
                      fx < volume.width && fy >= 0.0 && fy < volume.height && fabsf(r) <= 65504.0f;
  const std::int32_t cell =
      inside ? static_cast<std::int32_t>(fy) * volume.width + static_cast<std::int32_t>(fx) : -1;
  point_cell[i] = cell;
  if (inside) atomicMin(first_point + cell, static_cast<std::uint32_t>(i));
}

// first_flags[i] = 1 where point i is the first point of its cell.
static __global__ void __launch_bounds__(kPointThreads)
    first_flags_kernel(const std::int32_t* __restrict__ point_cell, std::int64_t num_points,
                       const std::uint32_t* __restrict__ first_point,
                       std::int32_t* __restrict__ first_flags) {
  const std::int64_t i = std::int64_t{blockIdx.x} * kPointThreads + threadIdx.x;
  if (i >= num_points) return;
  const std::int32_t cell = point_cell[i];
  first_flags[i] = cell >= 0 && first_point[cell] == static_cast<std::uint32_t>(i) ? 1 : 0;
}

// The first point of each cell names its pillar: pillar_of_cell[cell] and pillar_cell[pillar].
static __global__ void __launch_bounds__(kPointThreads)
    number_pillars_kernel(const std::int32_t* __restrict__ point_cell, std::int64_t num_points,
                          const std::uint32_t* __restrict__ first_point,
                          const std::int32_t* __restrict__ pillar_ids,
                          std::int32_t* __restrict__ pillar_of_cell,
                          std::int32_t* __restrict__ pillar_cell) {
  const std::int64_t i = std::int64_t{blockIdx.x} * kPointThreads + threadIdx.x;
  if (i >= num_points) return;
  const std::int32_t cell = point_cell[i];
  if (cell < 0 || first_point[cell] != static_cast<std::uint32_t>(i)) return;
  const std::int32_t pillar = pillar_ids[i];
  pillar_of_cell[cell] = pillar;
  pillar_cell[pillar] = cell;
}

// point_pillar[i]: flat cell -> pillar (or -1); pillar_size counts the points.
static __global__ void __launch_bounds__(kPointThreads)
    assign_kernel(std::int32_t* __restrict__ point_pillar, std::int64_t num_points,
                  const std::int32_t* __restrict__ pillar_of_cell,
                  std::int32_t* __restrict__ pillar_size) {
  const std::int64_t i = std::int64_t{blockIdx.x} * kPointThreads + threadIdx.x;
  if (i >= num_points) return;
  const std::int32_t cell = point_pillar[i];
  if (cell < 0) return;
  const std::int32_t pillar = pillar_of_cell[cell];
  point_pillar[i] = pillar;
  atomicAdd(pillar_size + pillar, 1);
}

// Each point into its pillar's segment, at a position the atomics choose.
static __global__ void __launch_bounds__(kPointThreads)
    place_kernel(const std::int32_t* __restrict__ point_pillar, std::int64_t num_points,
                 const std::int32_t* __restrict__ pillar_begin,
                 std::int32_t* __restrict__ pillar_cursor, std::int32_t* __restrict__ members) {
  const std::int64_t i = std::int64_t{blockIdx.x} * kPointThreads + threadIdx.x;
  if (i >= num_points) return;
  const std::int32_t pillar = point_pillar[i];
  if (pillar < 0) return;
  const std::int32_t slot = atomicAdd(pillar_cursor + pillar, 1);
  members[pillar_begin[pillar] + slot] = static_cast<std::int32_t>(i);
}

// sorted[begin + rank] = i, rank = the points of i's pillar with a smaller index.
static __global__ void __launch_bounds__(kPointThreads)
    rank_kernel(const std::int32_t* __restrict__ point_pillar, std::int64_t num_points,
                const std::int32_t* __restrict__ pillar_begin,
                const std::int32_t* __restrict__ pillar_size,
                const std::int32_t* __restrict__ members, std::int32_t* __restrict__ sorted) {
  const std::int64_t i = std::int64_t{blockIdx.x} * kPointThreads + threadIdx.x;
  if (i >= num_points) return;
  const std::int32_t pillar = point_pillar[i];
  if (pillar < 0) return;
  const std::int32_t* segment = members + pillar_begin[pillar];
  const std::int32_t size = pillar_size[pillar];
  const auto index = static_cast<std::int32_t>(i);
  std::int32_t rank = 0;
  for (std::int32_t j = 0; j < size; ++j) rank += segment[j] < index ? 1 : 0;
  sorted[pillar_begin[pillar] + rank] = index;
}

// Row q, slot k of the outputs, for q < rows, k < slots; totals[0] = n, the non-empty pillars.
static __global__ void __launch_bounds__(kPointThreads)
    output_kernel(const std::int32_t* __restrict__ totals, int max_pillars, std::int64_t rows,
                  int slots, int width, const std::int32_t* __restrict__ pillar_cell,
                  const std::int32_t* __restrict__ pillar_begin,
                  const std::int32_t* __restrict__ pillar_size,
                  const std::int32_t* __restrict__ sorted, std::int32_t* __restrict__ cell,
                  std::int32_t* __restrict__ point_index, std::int32_t* __restrict__ count,
                  std::int32_t* __restrict__ num_pillars) {
  const std::int64_t e = std::int64_t{blockIdx.x} * kPointThreads + threadIdx.x;
  if (e >= rows * slots) return;
  const std::int64_t q = e / slots;
  const std::int64_t k = e % slots;
  const std::int64_t nonempty = totals[0];
  const std::int64_t kept =
      max_pillars > 0 && nonempty > max_pillars ? std::int64_t{max_pillars} : nonempty;
  if (e == 0) *num_pillars = static_cast<std::int32_t>(kept);
  if (q >= kept) {
    point_index[e] = -1;
    if (k == 0) {
      cell[2 * q] = -1;
      cell[2 * q + 1] = -1;
      count[q] = 0;
    }
    return;
  }
  // host::select_positions in Inference mode, for the pillars and for the points.
  const std::int64_t pillar = kept == nonempty ? q : q * nonempty / kept;
  const std::int64_t size = pillar_size[pillar];
  const std::int32_t* points = sorted + pillar_begin[pillar];
  if (size <= slots) {
    point_index[e] = k < size ? points[k] : -1;
  } else {
    point_index[e] = points[k * size / slots];
  }
  if (k == 0) {
    const std::int32_t flat_cell = pillar_cell[pillar];
    cell[2 * q] = flat_cell / width;
    cell[2 * q + 1] = flat_cell % width;
    count[q] = static_cast<std::int32_t>(size < slots ? size : slots);
  }
}

std::int64_t pillar_gather_capacity(std::int64_t num_points, const GridSpec& grid,
                                    int max_pillars) {
  PS_CHECK(num_points >= 0 && max_pillars >= 0,
           "pillar_gather_capacity: expected M >= 0 points and P >= 0 pillars, given M = {}, "
           "P = {}",
           num_points, max_pillars);
  return max_pillars > 0 ? std::int64_t{max_pillars} : max_nonempty(num_points, grid.cells());
}

std::int64_t pillar_gather_workspace_size(std::int64_t num_points, const GridSpec& grid) {
  PS_CHECK(num_points >= 0, "pillar_gather_workspace_size: expected M >= 0 points, given {}",
           num_points);
  return workspace_size(num_points, grid.cells());
}

namespace {

constexpr std::int64_t kMaxIndex = std::numeric_limits<std::int32_t>::max();

void check_points_and_grid(const char* op, const float* points, std::int64_t num_points,
                           const GridSpec& grid) {
  PS_CHECK(num_points >= 0 && num_points < kMaxIndex,
           "{}: point indices are int32, so 0 to {} points, given {}", op, kMaxIndex - 1,
           num_points);
  const std::int64_t width = grid.width(), height = grid.height();
  PS_CHECK(std::isfinite(grid.cell) && grid.cell > 0.0 && width >= 1 && height >= 1 &&
               width * height <= kMaxIndex,
           "{}: the grid needs a positive cell size and between 1 and 2^31 - 1 cells, given cell "
           "{} and {} x {}",
           op, grid.cell, width, height);
  PS_CHECK(num_points == 0 || points != nullptr,
           "{}: points must point to {} floats (M x 4) of device memory", op, 4 * num_points);
}

void check_workspace(const char* op, std::int64_t num_points, const GridSpec& grid,
                     const std::int32_t* workspace, std::int64_t workspace_size_given) {
  const std::int64_t needed = workspace_size(num_points, grid.cells());
  PS_CHECK(workspace != nullptr && workspace_size_given >= needed,
           "{}: the workspace must hold pillar_gather_workspace_size(M, grid) = {} int32, given {} "
           "at {}",
           op, needed, workspace_size_given, static_cast<const void*>(workspace));
}

// The grouping steps, [cells] to [rank]; arguments checked by the caller.
PointGroups group(const float* points, std::int64_t num_points, const GridSpec& grid,
                  std::int32_t* workspace, cudaStream_t stream) {
  const std::int64_t width = grid.width(), height = grid.height();
  const std::int64_t cells = width * height;
  const std::int64_t rn = max_nonempty(num_points, cells);
  const Workspace w = carve(workspace, num_points, cells);
  const unsigned point_blocks = blocks_for(num_points, kPointThreads);
  if (num_points > 0) {
    const Volume volume{grid.x_min,
                        grid.x_max,
                        grid.y_min,
                        grid.y_max,
                        grid.z_min,
                        grid.z_max,
                        grid.cell,
                        static_cast<int>(width),
                        static_cast<int>(height)};
    PS_CUDA_CHECK(cudaMemsetAsync(w.first_point, 0xff,
                                  static_cast<std::size_t>(cells) * sizeof(std::uint32_t), stream));
    PS_CUDA_CHECK(cudaMemsetAsync(w.pillar_size, 0,
                                  static_cast<std::size_t>(rn) * sizeof(std::int32_t), stream));
    PS_CUDA_CHECK(cudaMemsetAsync(w.pillar_cursor, 0,
                                  static_cast<std::size_t>(rn) * sizeof(std::int32_t), stream));
    launch_kernel(cells_kernel, dim3(point_blocks), dim3(kPointThreads), 0, stream, points,
                  num_points, volume, w.point_pillar, w.first_point);
    launch_kernel(first_flags_kernel, dim3(point_blocks), dim3(kPointThreads), 0, stream,
                  w.point_pillar, num_points, w.first_point, w.first_flags);
  }
  exclusive_scan(w.first_flags, num_points, w.tile_sums, w.first_flags, w.totals, stream);
  if (num_points > 0) {
    launch_kernel(number_pillars_kernel, dim3(point_blocks), dim3(kPointThreads), 0, stream,
                  w.point_pillar, num_points, w.first_point, w.first_flags, w.pillar_of_cell,
                  w.pillar_cell);
    launch_kernel(assign_kernel, dim3(point_blocks), dim3(kPointThreads), 0, stream, w.point_pillar,
                  num_points, w.pillar_of_cell, w.pillar_size);
  }
  exclusive_scan(w.pillar_size, rn, w.tile_sums, w.pillar_begin, w.totals + 1, stream);
  if (num_points > 0) {
    launch_kernel(place_kernel, dim3(point_blocks), dim3(kPointThreads), 0, stream, w.point_pillar,
                  num_points, w.pillar_begin, w.pillar_cursor, w.members);
    launch_kernel(rank_kernel, dim3(point_blocks), dim3(kPointThreads), 0, stream, w.point_pillar,
                  num_points, w.pillar_begin, w.pillar_size, w.members, w.sorted);
  }
  return PointGroups{w.sorted, w.pillar_begin, w.pillar_size, w.pillar_cell, w.totals, rn};
}

}  // namespace

PointGroups group_points(const float* points, std::int64_t num_points, const GridSpec& grid,
                         std::int32_t* workspace, std::int64_t workspace_size_given,
                         cudaStream_t stream) {
  constexpr const char* kOp = "group_points";
  check_points_and_grid(kOp, points, num_points, grid);
  check_workspace(kOp, num_points, grid, workspace, workspace_size_given);
  return group(points, num_points, grid, workspace, stream);
}

void pillar_gather(const float* points, std::int64_t num_points, const GridSpec& grid,
                   int max_points_per_pillar, int max_pillars, std::int32_t* cell,
                   std::int32_t* point_index, std::int32_t* count, std::int32_t* num_pillars,
                   std::int32_t* workspace, std::int64_t workspace_size_given,
                   cudaStream_t stream) {
  constexpr const char* kOp = "pillar_gather";
  PS_CHECK(max_points_per_pillar >= 1, "{}: max_points_per_pillar (N) must be >= 1, given {}", kOp,
           max_points_per_pillar);
  PS_CHECK(max_pillars >= 0, "{}: max_pillars (P) must be >= 0 (0 keeps every pillar), given {}",
           kOp, max_pillars);
  check_points_and_grid(kOp, points, num_points, grid);
  const std::int64_t rows = pillar_gather_capacity(num_points, grid, max_pillars);
  PS_CHECK(ceil_div(rows * max_points_per_pillar, std::int64_t{kPointThreads}) <= kMaxIndex,
           "{}: R = {} rows of N = {} slots exceed the grid", kOp, rows, max_points_per_pillar);
  check_workspace(kOp, num_points, grid, workspace, workspace_size_given);
  PS_CHECK(num_pillars != nullptr &&
               (rows == 0 || (cell != nullptr && point_index != nullptr && count != nullptr)),
           "{}: cell ({} int32), point_index ({} int32), count ({} int32) and num_pillars (1 "
           "int32) must be device memory",
           kOp, 2 * rows, rows * max_points_per_pillar, rows);

  const PointGroups groups = group(points, num_points, grid, workspace, stream);
  if (rows == 0) {
    PS_CUDA_CHECK(cudaMemsetAsync(num_pillars, 0, sizeof(std::int32_t), stream));
    return;
  }
  launch_kernel(output_kernel, dim3(blocks_for(rows * max_points_per_pillar, kPointThreads)),
                dim3(kPointThreads), 0, stream, groups.num_pillars, max_pillars, rows,
                max_points_per_pillar, static_cast<int>(grid.width()), groups.pillar_cell,
                groups.pillar_begin, groups.pillar_size, groups.sorted, cell, point_index, count,
                num_pillars);
}

}  // namespace pillarseg::cuda
