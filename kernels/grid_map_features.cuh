// The six grid-map layers of Bieder et al. 2020 (host/grid_map_features.hpp is the spec), per cell
// of the (H, W) grid: log(1 + detections), log(1 + transmissions), mean reflectance, min z and max
// z of the points inside the grid volume, detections / (detections + transmissions):
//   points (M, 4), detections, transmissions (H, W) uint32 -> out (6, H, W) float.
// The points of each cell are the pillar gather's groups (kernels/pillar_gather.cuh,
// group_points): one thread per non-empty cell sums its reflectances in double in input order, as
// the host does, so the mean is the host's bit for bit; min and max are exact; the ratio is one
// IEEE division. The GPU's log1p may differ from the host's by an ulp of the double, and so the
// float by one ulp in rare cells; the emulation uses the host's. Pointers are device memory; the
// work is queued on `stream`.
#pragma once

#include <cstdint>

#include "core/grid.hpp"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

inline constexpr int kGridMapLayers = 6;

// workspace: pillar_gather_workspace_size(M, grid) int32 (the groups live there).
void grid_map_features(const float* points, std::int64_t num_points, const GridSpec& grid,
                       const std::uint32_t* detections, const std::uint32_t* transmissions,
                       float* out, std::int32_t* workspace, std::int64_t workspace_size,
                       cudaStream_t stream);

}  // namespace pillarseg::cuda
