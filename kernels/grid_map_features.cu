// The grid-map layers (see grid_map_features.cuh) in two kernels: one thread per cell writes the
// ray-count layers and zeros the point layers, then one thread per non-empty cell (a group of the
// pillar gather's grouping) walks its points in input order and writes the point layers.
#include "kernels/grid_map_features.cuh"

#include <cmath>
#include <cstdint>

#include "kernels/common.cuh"
#include "kernels/float4_split.cuh"
#include "kernels/pillar_gather.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
// Layers 0, 1 and 5 from the ray counts; 2, 3 and 4 zero (cells without points).
static __global__ void __launch_bounds__(kElementwiseBlock)
    ray_layers_kernel(const std::uint32_t* __restrict__ detections,
                      const std::uint32_t* __restrict__ transmissions, std::int64_t cells,
                      float* __restrict__ out) {
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  for (std::int64_t c = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x; c < cells;
       c += stride) {
    const double det = detections[c], trans = transmissions[c];
    out[0 * cells + c] = static_cast<float>(log1p(det));
    out[1 * cells + c] = static_cast<float>(log1p(trans));
    out[2 * cells + c] = 0.0f;
    out[3 * cells + c] = 0.0f;
    out[4 * cells + c] = 0.0f;
    out[5 * cells + c] = det + trans > 0 ? static_cast<float>(det / (det + trans)) : 0.0f;
  }
}

// Layers 2, 3 and 4 of the cell of each group p < n.
static __global__ void __launch_bounds__(kElementwiseBlock)
    point_layers_kernel(const float* __restrict__ points, PointGroups groups, std::int64_t cells,
                        float* __restrict__ out) {
  const std::int64_t n = groups.num_pillars[0];
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  for (std::int64_t p = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x; p < n; p += stride) {
    const std::int32_t* members = groups.sorted + groups.pillar_begin[p];
    const std::int32_t size = groups.pillar_size[p];
    double reflectance = 0.0;
    float z_min = points[4 * std::int64_t{members[0]} + 2], z_max = z_min;
    for (std::int32_t k = 0; k < size; ++k) {
      const float* point = points + 4 * std::int64_t{members[k]};
      reflectance += point[3];
      z_min = fminf(z_min, point[2]);
      z_max = fmaxf(z_max, point[2]);
    }
    const std::int64_t c = groups.pillar_cell[p];
    out[2 * cells + c] = static_cast<float>(reflectance / size);
    out[3 * cells + c] = z_min;
    out[4 * cells + c] = z_max;
  }
}

void grid_map_features(const float* points, std::int64_t num_points, const GridSpec& grid,
                       const std::uint32_t* detections, const std::uint32_t* transmissions,
                       float* out, std::int32_t* workspace, std::int64_t workspace_size,
                       cudaStream_t stream) {
  const std::int64_t cells = grid.cells();
  PS_CHECK(cells >= 1 && detections != nullptr && transmissions != nullptr && out != nullptr,
           "grid_map_features: detections, transmissions ({} uint32 each) and out (6 x {} "
           "floats) must be device memory",
           cells, cells);
  const PointGroups groups =
      group_points(points, num_points, grid, workspace, workspace_size, stream);
  launch_kernel(ray_layers_kernel, elementwise_grid(cells),
                dim3(kElementwiseBlock), 0, stream, detections, transmissions, cells, out);
  if (groups.capacity == 0) return;
  launch_kernel(point_layers_kernel, elementwise_grid(groups.capacity),
                dim3(kElementwiseBlock), 0, stream, points, groups, cells, out);
}

}  // namespace pillarseg::cuda
