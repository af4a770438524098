// Point decoration (the input of OpenPCDet's PillarVFE; host/point_decoration.hpp is the spec):
//   points (M, 4) float rows (x, y, z, r); pillars from the pillar gather: cell (P, 2) int32 rows
//   (iy, ix), point_index (P, N) int32, count (P) int32 -> out (P, N, 10) float, where the row of
//   slot k < count(p) holds, for the point q = points[point_index(p, k)],
//     x, y, z, r,
//     x - mean_x, y - mean_y, z - mean_z   (mean over the pillar's kept points, summed in slot
//                                           order in double, as the host does),
//     x - cx, y - cy, z - cz               (pillar centre cx = x_min + (ix + 0.5) cell, cy
//                                           likewise, cz = the middle of [z_min, z_max)),
//   and every padding row (slot >= count(p)) is all zero.
// The pillar arrays come from kernels/pillar_gather.cu, whose unused rows have count 0 (all-zero
// output rows). A kernel cannot throw, so a pillar the host would refuse (count outside [0, N],
// or a kept index outside [0, M)) is written all zero instead of reading outside the points.
// Every output element has one writer: deterministic. Pointers are device memory; the work is
// queued on `stream`.
#pragma once

#include <cstdint>

#include "core/grid.hpp"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// D, the features of a decorated point.
inline constexpr std::int64_t kDecoratedFeatures = 10;

// points (M, 4), cell (P, 2), point_index (P, N), count (P) -> out (P, N, 10); `grid` gives the
// pillar centres (x_min, y_min, cell, z_min, z_max). live_pillars: nullptr, or one int32 of
// device memory (the gather's P', read when the kernel runs): pillars at or past it are inert
// and their rows of out are left as they are.
void decorate_points(const float* points, std::int64_t num_points, const std::int32_t* cell,
                     const std::int32_t* point_index, const std::int32_t* count,
                     std::int64_t pillars, std::int64_t slots, const GridSpec& grid, float* out,
                     cudaStream_t stream, const std::int32_t* live_pillars = nullptr);

}  // namespace pillarseg::cuda
