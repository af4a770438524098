// Point decoration: points (M, 4) and pillars (P, N slots) -> (P, N, 10) (see
// point_decoration.cuh). A block decorates kPillarsPerBlock consecutive pillars, whose output is
// one contiguous run of kPillarsPerBlock N 10 floats: first one thread per pillar sums its points
// in slot order (in double, as the host) into shared memory, then all threads write the run with
// consecutive threads on consecutive floats (coalesced stores; the few point rows they read stay
// in L1).
#include "kernels/point_decoration.cuh"

#include <cmath>
#include <cstdint>
#include <limits>

#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kBlockSize = 256;
constexpr int kPillarsPerBlock = 32;
constexpr int kFeatures = static_cast<int>(kDecoratedFeatures);

// What the kernel needs of the grid, in the host's double precision.
struct PillarCentres {
  double x_min = 0.0, y_min = 0.0, cell = 0.0;
  double centre_z = 0.0;  // z_min + (z_max - z_min) / 2, computed on the host as the host does
};

}  // namespace

// Pillars [kPillarsPerBlock blockIdx.x, + kPillarsPerBlock) -> their rows of out.
static __global__ void __launch_bounds__(kBlockSize)
    decorate_points_kernel(const float* __restrict__ points, std::int64_t num_points,
                           const std::int32_t* __restrict__ cell,
                           const std::int32_t* __restrict__ point_index,
                           const std::int32_t* __restrict__ count, std::int64_t pillars, int slots,
                           const std::int32_t* __restrict__ live_pillars, PillarCentres centres,
                           float* __restrict__ out) {
  __shared__ double mean[kPillarsPerBlock][3];
  __shared__ int kept[kPillarsPerBlock];  // count, or 0 for a pillar that is written all zero
  const std::int64_t p0 = std::int64_t{blockIdx.x} * kPillarsPerBlock;
  if (live_pillars != nullptr && *live_pillars < pillars) pillars = *live_pillars;
  if (p0 >= pillars) return;  // every pillar of the block is inert: left as it is
  const int block_pillars =
      pillars - p0 < kPillarsPerBlock ? static_cast<int>(pillars - p0) : kPillarsPerBlock;
  const int t = static_cast<int>(threadIdx.x);
  if (t < block_pillars) {
    const std::int64_t p = p0 + t;
    int n = count[p];
    double sum_x = 0.0, sum_y = 0.0, sum_z = 0.0;
    if (n < 0 || n > slots) n = 0;
    for (int k = 0; k < n; ++k) {
      const std::int32_t index = point_index[p * slots + k];
      if (index < 0 || index >= num_points) {
        n = 0;
        break;
      }
      sum_x += points[4 * std::int64_t{index}];
      sum_y += points[4 * std::int64_t{index} + 1];
      sum_z += points[4 * std::int64_t{index} + 2];
    }
    kept[t] = n;
    mean[t][0] = n > 0 ? sum_x / n : 0.0;
    mean[t][1] = n > 0 ? sum_y / n : 0.0;
    mean[t][2] = n > 0 ? sum_z / n : 0.0;
  }
  __syncthreads();
  const int row_floats = slots * kFeatures;
  const int block_floats = block_pillars * row_floats;
  float* block_out = out + p0 * row_floats;
  for (int e = t; e < block_floats; e += kBlockSize) {
    const int local = e / row_floats;
    const int slot = e % row_floats / kFeatures;
    const int feature = e % kFeatures;
    float value = 0.0f;
    if (slot < kept[local]) {
      const std::int64_t p = p0 + local;
      const std::int64_t index = point_index[p * slots + slot];
      const float* q = points + 4 * index;
      if (feature < 4) {
        value = q[feature];
      } else if (feature < 7) {
        value = static_cast<float>(static_cast<double>(q[feature - 4]) - mean[local][feature - 4]);
      } else if (feature == 7) {
        const double centre_x = centres.x_min + (cell[2 * p + 1] + 0.5) * centres.cell;
        value = static_cast<float>(static_cast<double>(q[0]) - centre_x);
      } else if (feature == 8) {
        const double centre_y = centres.y_min + (cell[2 * p] + 0.5) * centres.cell;
        value = static_cast<float>(static_cast<double>(q[1]) - centre_y);
      } else {
        value = static_cast<float>(static_cast<double>(q[2]) - centres.centre_z);
      }
    }
    block_out[e] = value;
  }
}

void decorate_points(const float* points, std::int64_t num_points, const std::int32_t* cell,
                     const std::int32_t* point_index, const std::int32_t* count,
                     std::int64_t pillars, std::int64_t slots, const GridSpec& grid, float* out,
                     cudaStream_t stream, const std::int32_t* live_pillars) {
  constexpr const char* kOp = "decorate_points";
  PS_CHECK(num_points >= 0 && pillars >= 0,
           "{}: expected M >= 0 points and P >= 0 pillars, given M = {}, P = {}", kOp, num_points,
           pillars);
  PS_CHECK(slots >= 1 && slots * kDecoratedFeatures * kPillarsPerBlock <=
                             std::numeric_limits<std::int32_t>::max(),
           "{}: expected 1 <= N <= {} points per pillar, given N = {}", kOp,
           std::numeric_limits<std::int32_t>::max() / (kDecoratedFeatures * kPillarsPerBlock),
           slots);
  PS_CHECK(
      ceil_div(pillars, std::int64_t{kPillarsPerBlock}) <= std::numeric_limits<std::int32_t>::max(),
      "{}: P = {} pillars exceed the grid", kOp, pillars);
  PS_CHECK(std::isfinite(grid.cell) && grid.cell > 0.0,
           "{}: the grid cell must be a positive size, given {}", kOp, grid.cell);
  if (pillars == 0) return;
  PS_CHECK(cell != nullptr && point_index != nullptr && count != nullptr && out != nullptr,
           "{}: cell ({} int32), point_index ({} int32), count ({} int32) and out ({} floats) "
           "must be device memory",
           kOp, 2 * pillars, pillars * slots, pillars, pillars * slots * kDecoratedFeatures);
  PS_CHECK(num_points == 0 || points != nullptr,
           "{}: points must point to {} floats (M x 4) of device memory", kOp, 4 * num_points);
  const PillarCentres centres{grid.x_min, grid.y_min, grid.cell,
                              grid.z_min + 0.5 * (grid.z_max - grid.z_min)};
  launch_kernel(decorate_points_kernel,
                dim3(static_cast<unsigned>(ceil_div(pillars, std::int64_t{kPillarsPerBlock}))),
                dim3(kBlockSize), 0, stream, points, num_points, cell, point_index, count, pillars,
                static_cast<int>(slots), live_pillars, centres, out);
}

}  // namespace pillarseg::cuda
