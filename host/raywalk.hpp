// Ray walks through the top-view grid (Amanatides & Woo; DESIGN.md section 1, "Observability
// (2D)" and "Occupancy (3D)"). One ray goes from the sensor origin to each finite point:
// - 2D: per cell (H, W), transmissions (cells a ray passes before its end cell) and detections
//   (a ray's end cell, when the point lies in the grid); the observability map is their sum.
// - 3D: per voxel (Z, H, W), Z = grid.layers(), hits (end voxel, when the point lies in the
//   volume) and passes (voxels before the end voxel), and the occupancy probability from them.
//
// The walk, exactly (every ray walk of the engine, host or kernel, visits these cells):
// - Cell coordinates, in double precision: u = (x - x_min) / cell, v = (y - y_min) / cell,
//   w = (z - z_min) / voxel_z, for the origin o and the point p. The ray is the segment
//   o + t * (p - o), t in [0, 1]; the 2D walk ignores w.
// - First cell, per axis: floor(o), or ceil(o) - 1 where p - o < 0 on that axis: the cell the
//   ray enters from the origin, which for an origin on a cell boundary (the default origin
//   (0, 0, 0) lies on cell corners) depends on the direction. Where p - o = 0 on an axis, the
//   ray stays in cell floor(o) of that axis, also when it runs along a cell border.
// - Last cell: floor(p), as GridSpec::ix / iy / iz.
// - In between, one axis step at a time, the cells the segment crosses: |dix| + |diy| (+ |diz|)
//   + 1 cells in all. A ray whose first and last cells coincide has that one cell.
// - Ties: where the segment crosses boundaries of several axes at the same t (it passes exactly
//   through a cell corner, or in 3D a voxel edge or corner), the walk steps x first, then y,
//   then z. So a ray with dx > 0, dy > 0 through the corner shared by cells (i, j) and
//   (i + 1, j + 1) visits (i + 1, j) between them, and one with dx < 0, dy > 0 through the
//   corner shared by (i, j) and (i - 1, j + 1) visits (i - 1, j).
// - Every crossing is decided exactly for the segment between the double cell coordinates of
//   o and p: a double evaluation, and where that lies within rounding of a tie, the exact sign
//   of the orientation (error-free products and expansion sums).
// - Only cells inside the grid count: the walk is clipped to the grid box (rays from far points,
//   or from an origin outside the grid, cost only their in-grid cells) and visits exactly the
//   in-grid cells of the unclipped walk. A detection or hit needs the point inside the grid
//   (GridSpec::contains_xy in 2D, GridSpec::contains in 3D).
//
// Counts are made in parallel over bands of grid rows, each band owned by one thread that walks
// the part of every ray inside it, so the counts are identical for every thread count.
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include "core/eigen.hpp"
#include "core/grid.hpp"
#include "core/point.hpp"
#include "core/tensor.hpp"

namespace pillarseg::host {

// Per-cell ray counts on the (H, W) grid.
struct ObservabilityCounts {
  Tensor<uint32_t> transmissions;  // (H, W): rays that passed the cell before their end cell
  Tensor<uint32_t> detections;     // (H, W): rays that ended in the cell
};

// points: M points in the LiDAR frame (non-finite ones are skipped); origin: the sensor origin
// in the same frame, anywhere (inside the grid or not). z plays no part.
ObservabilityCounts observability_2d(std::span<const Point> points,
                                     const Eigen::Vector3d& origin, const GridSpec& grid);

namespace raywalk_detail {
struct SweepBuffers;
}

// Scratch memory of observability_2d, reusable across scans: each point's ray classified, then
// sorted into sweeps (about 43 bytes per point in all), and each thread's working rows. One workspace per calling thread; a
// steady-state loop that keeps it (and the output) allocates nothing once the buffers have grown.
class ObservabilityWorkspace {
 public:
  ObservabilityWorkspace();
  ~ObservabilityWorkspace();
  ObservabilityWorkspace(ObservabilityWorkspace&&) noexcept;
  ObservabilityWorkspace& operator=(ObservabilityWorkspace&&) noexcept;
  ObservabilityWorkspace(const ObservabilityWorkspace&) = delete;
  ObservabilityWorkspace& operator=(const ObservabilityWorkspace&) = delete;

  raywalk_detail::SweepBuffers& buffers();  // (made again after a move)

 private:
  std::unique_ptr<raywalk_detail::SweepBuffers> buffers_;
};

// Same, with caller-owned scratch and output: `out` is overwritten (its tensors keep their
// allocations) with the same counts.
void observability_2d(std::span<const Point> points, const Eigen::Vector3d& origin,
                      const GridSpec& grid, ObservabilityWorkspace& workspace,
                      ObservabilityCounts& out);

// (H, W): transmissions + detections per cell, the number of rays that touched the cell.
Tensor<uint32_t> observability_map(const ObservabilityCounts& counts);

// Per-voxel ray counts on the (Z, H, W) voxel grid, voxels cell x cell x voxel_z.
struct OccupancyCounts {
  Tensor<uint32_t> hits;    // (Z, H, W): rays that ended in the voxel
  Tensor<uint32_t> passes;  // (Z, H, W): rays that passed the voxel before their end voxel
};

// points: M points in the LiDAR frame (non-finite ones are skipped); origin: the sensor origin.
OccupancyCounts occupancy_counts_3d(std::span<const Point> points, const Eigen::Vector3d& origin,
                                    const GridSpec& grid);

// (Z, H, W): occupancy probability 1 / (1 + exp(-l)), l = hits * log(0.7 / 0.3) +
// passes * log(0.4 / 0.6) (evaluated in double); 0.5 where no ray touched the voxel.
Tensor<float> occupancy_probability(const OccupancyCounts& counts);

// One visited cell of a single ray's walk (iz = 0 in 2D).
struct WalkCell {
  int64_t ix = 0, iy = 0, iz = 0;
  bool operator==(const WalkCell&) const = default;
};

// The in-grid cells of one ray's 2D walk, in walk order; the last one is the ray's end cell
// when that lies in the grid index range. The reference the bulk counts and the kernels are
// checked against; allocates, so meant for tests and tools, not for scans.
std::vector<WalkCell> ray_cells_2d(const Eigen::Vector3d& origin, const Eigen::Vector3d& point,
                                   const GridSpec& grid);

// The in-volume voxels of one ray's 3D walk, in walk order, likewise.
std::vector<WalkCell> ray_voxels_3d(const Eigen::Vector3d& origin, const Eigen::Vector3d& point,
                                    const GridSpec& grid);

}  // namespace pillarseg::host
