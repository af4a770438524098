// Ray walks through the top-view grid (Amanatides & Woo; host/raywalk.hpp is the spec and defines
// the walk exactly: first and last cells, one axis step at a time, ties stepping x, then y, then
// z, crossings decided exactly, only in-grid cells counted). One ray from the sensor origin to
// each point with finite x, y, z; points (M, 4) float rows (x, y, z, r):
//   2D: transmissions (H, W) uint32, the rays that passed a cell before their end cell, and
//       detections (H, W) uint32, the rays that ended in it with the point inside the grid
//       (GridSpec::contains_xy); the observability map (H, W) is their sum;
//   3D: passes and hits (Z, H, W) uint32 likewise on the voxel grid (GridSpec::contains for a
//       hit); the occupancy probability (Z, H, W) float from them.
// One thread per ray. Counts are integers combined with atomics, as differences along runs of
// cells and prefix sums after (mod 2^32, exact while the counts fit uint32): the same counts as
// the host for any scheduling. Pointers are device memory; the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "core/grid.hpp"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// Where the rays start, in the frame of the points.
struct SensorOrigin {
  double x = 0.0, y = 0.0, z = 0.0;
};

// The uint32 scratch of observability_2d: H W.
std::int64_t observability_2d_workspace_size(const GridSpec& grid);

// points (M, 4) -> transmissions (H, W), detections (H, W) (both overwritten); workspace holds
// observability_2d_workspace_size(grid) uint32.
void observability_2d(const float* points, std::int64_t num_points, const SensorOrigin& origin,
                      const GridSpec& grid, std::uint32_t* transmissions, std::uint32_t* detections,
                      std::uint32_t* workspace, std::int64_t workspace_size, cudaStream_t stream);

// transmissions, detections (n) -> map (n) = their sum: the rays that touched each cell.
void observability_map(const std::uint32_t* transmissions, const std::uint32_t* detections,
                       std::int64_t n, std::uint32_t* map, cudaStream_t stream);

// points (M, 4) -> hits (Z, H, W), passes (Z, H, W) (both overwritten), Z = grid.layers().
void occupancy_counts_3d(const float* points, std::int64_t num_points, const SensorOrigin& origin,
                         const GridSpec& grid, std::uint32_t* hits, std::uint32_t* passes,
                         cudaStream_t stream);

// hits, passes (n) -> probability (n) = 1 / (1 + exp(-l)), l = hits log(0.7 / 0.3) +
// passes log(0.4 / 0.6) in double; 0.5 where no ray touched the voxel. The GPU's exp may differ
// from the host's by an ulp of the double, so the float can differ from the host's by one ulp.
void occupancy_probability(const std::uint32_t* hits, const std::uint32_t* passes, std::int64_t n,
                           float* probability, cudaStream_t stream);

}  // namespace pillarseg::cuda
