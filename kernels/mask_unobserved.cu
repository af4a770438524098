// Masking of unobserved cells (see mask_unobserved.cuh): one grid-stride loop over the cells; a masked
// cell clears its label and its value in every probability plane.
#include "kernels/mask_unobserved.cuh"

#include <cstdint>

#include "kernels/common.cuh"
#include "kernels/float4_split.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
static __global__ void __launch_bounds__(kElementwiseBlock)
    mask_unobserved_kernel(const std::uint32_t* __restrict__ transmissions,
                           const std::uint32_t* __restrict__ detections, std::int64_t n,
                           std::uint8_t* __restrict__ labels, float* __restrict__ probabilities,
                           std::int64_t planes) {
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  for (std::int64_t i = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x; i < n; i += stride) {
    if (transmissions[i] + detections[i] != 0u) continue;
    labels[i] = 0;
    for (std::int64_t k = 0; k < planes; ++k) probabilities[k * n + i] = 0.0f;
  }
}

void mask_unobserved(const std::uint32_t* transmissions, const std::uint32_t* detections,
                     std::int64_t n, std::uint8_t* labels, float* probabilities,
                     std::int64_t planes, cudaStream_t stream) {
  PS_CHECK(n >= 0 && planes >= 0,
           "mask_unobserved: expected n >= 0 cells and planes >= 0, given n = {}, planes = {}", n,
           planes);
  PS_CHECK(n == 0 || (transmissions != nullptr && detections != nullptr && labels != nullptr &&
                      (planes == 0 || probabilities != nullptr)),
           "mask_unobserved: transmissions, detections ({} uint32 each), labels ({} bytes) and "
           "{} probability planes must be device memory",
           n, n, planes);
  if (n == 0) return;
  launch_kernel(mask_unobserved_kernel, elementwise_grid(n),
                dim3(kElementwiseBlock), 0, stream, transmissions, detections, n, labels,
                planes > 0 ? probabilities : nullptr, planes);
}

}  // namespace pillarseg::cuda
