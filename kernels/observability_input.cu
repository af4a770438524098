// The 2D occupancy input (see observability_input.cuh): one grid-stride loop over the cells.
#include "kernels/observability_input.cuh"

#include <cmath>
#include <cstdint>

#include "kernels/common.cuh"
#include "kernels/float4_split.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
static __global__ void __launch_bounds__(kElementwiseBlock)
    observability_input_kernel(const std::uint32_t* __restrict__ transmissions,
                               const std::uint32_t* __restrict__ detections, std::int64_t n,
                               float* __restrict__ out) {
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  for (std::int64_t i = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x; i < n; i += stride) {
    const std::uint32_t rays = transmissions[i] + detections[i];
    out[i] = static_cast<float>(log1p(static_cast<double>(rays)));
  }
}

void observability_input(const std::uint32_t* transmissions, const std::uint32_t* detections,
                         std::int64_t n, float* out, cudaStream_t stream) {
  PS_CHECK(n >= 0, "observability_input: expected n >= 0 cells, given {}", n);
  PS_CHECK(n == 0 || (transmissions != nullptr && detections != nullptr && out != nullptr),
           "observability_input: transmissions, detections ({} uint32 each) and out ({} floats) "
           "must be device memory",
           n, n);
  if (n == 0) return;
  launch_kernel(observability_input_kernel, elementwise_grid(n),
                dim3(kElementwiseBlock), 0, stream, transmissions, detections, n, out);
}

}  // namespace pillarseg::cuda
