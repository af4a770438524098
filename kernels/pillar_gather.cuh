// Pillar gather (PointPillars / OpenPCDet semantics; host/pillar_gather.hpp is the spec), in the
// deterministic inference mode of the host (SampleMode::Inference; the seeded random subsets of
// Training mode are drawn on the host):
//   points (M, 4) float rows (x, y, z, r) -> R rows of pillars, R = pillar_gather_capacity(M,
//   grid, P): cell (R, 2) int32 rows (iy, ix), point_index (R, N) int32, count (R) int32, and
//   *num_pillars = P' (one int32).
// Only points with GridSpec::contains(x, y, z) (tested in double exactly as the host) belong to a
// pillar. Pillars are numbered in order of first appearance in the input; with more than P
// non-empty pillars (P > 0), the P' = P kept are those at positions floor(q n / P), q < P, of the
// n in that order; a pillar with s > N points keeps the points at ranks floor(k s / N), k < N, of
// its points in input order, else all s. Rows q < P' equal the host's output bit for bit; rows
// q >= P' are unused: cell (-1, -1) (which kernels/scatter.cu skips), count 0, point_index -1.
// Deterministic: no order that atomics choose reaches an output (see pillar_gather.cu). Pointers
// are device memory; the work is queued on `stream`; nothing waits for the device.
#pragma once

#include <cstdint>

#include "core/grid.hpp"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// R, the rows of the outputs: P when max_pillars P > 0, else min(M, W H), room for every
// non-empty pillar.
std::int64_t pillar_gather_capacity(std::int64_t num_points, const GridSpec& grid, int max_pillars);

// The int32 scratch pillar_gather needs for M points on `grid` (about 2 W H + 8 M).
std::int64_t pillar_gather_workspace_size(std::int64_t num_points, const GridSpec& grid);

// The inside points grouped by cell, pillars numbered by first appearance: what the gather's first
// steps leave in its workspace (valid until the workspace is used again), read by the grid-map
// layers (kernels/grid_map_features.cu). Device pointers.
struct PointGroups {
  const std::int32_t* sorted = nullptr;        // (M): the points of pillar 0, then 1, ..., each
                                               // pillar's in input order
  const std::int32_t* pillar_begin = nullptr;  // (Rn): pillar p's first entry in sorted
  const std::int32_t* pillar_size = nullptr;   // (Rn): its number of points
  const std::int32_t* pillar_cell = nullptr;   // (Rn): its flat cell iy W + ix
  const std::int32_t* num_pillars = nullptr;   // (1): n, the non-empty pillars (p < n are valid)
  std::int64_t capacity = 0;                   // Rn = min(M, W H)
};

// points (M, 4) -> the groups, in workspace (pillar_gather_workspace_size(M, grid) int32).
PointGroups group_points(const float* points, std::int64_t num_points, const GridSpec& grid,
                         std::int32_t* workspace, std::int64_t workspace_size, cudaStream_t stream);

// points (M, 4) -> cell (R, 2), point_index (R, N), count (R), num_pillars (1), with
// N = max_points_per_pillar >= 1, P = max_pillars >= 0 (0 keeps every non-empty pillar) and R
// as pillar_gather_capacity; workspace holds pillar_gather_workspace_size(M, grid) int32.
void pillar_gather(const float* points, std::int64_t num_points, const GridSpec& grid,
                   int max_points_per_pillar, int max_pillars, std::int32_t* cell,
                   std::int32_t* point_index, std::int32_t* count, std::int32_t* num_pillars,
                   std::int32_t* workspace, std::int64_t workspace_size, cudaStream_t stream);

}  // namespace pillarseg::cuda
