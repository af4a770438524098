// Test-time flips' sum (see mirror_add.cuh): consecutive threads write consecutive elements of the
// sum and read consecutive elements of x's row (backwards where mirror_x).
#include "kernels/mirror_add.cuh"

#include <cstdint>

#include "kernels/common.cuh"
#include "kernels/float4_split.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

static __global__ void __launch_bounds__(kElementwiseBlock)
    mirror_add_kernel(const float* __restrict__ x, std::int64_t n, std::int64_t height,
                      std::int64_t width, bool mirror_y, bool mirror_x, float* __restrict__ sum) {
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  for (std::int64_t i = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x; i < n; i += stride) {
    const std::int64_t ix = i % width, row = i / width;  // row = plane * height + iy
    const std::int64_t iy = row % height, plane_start = row - iy;
    const std::int64_t sy = mirror_y ? height - 1 - iy : iy, sx = mirror_x ? width - 1 - ix : ix;
    sum[i] += x[(plane_start + sy) * width + sx];
  }
}

void mirror_add(const float* x, std::int64_t planes, std::int64_t height, std::int64_t width,
                bool mirror_y, bool mirror_x, float* sum, cudaStream_t stream) {
  PS_CHECK(planes >= 0 && height >= 0 && width >= 0,
           "mirror_add: expected (planes, height, width) >= 0, given ({}, {}, {})", planes, height,
           width);
  const std::int64_t n = planes * height * width;
  if (n == 0) return;
  PS_CHECK(x != nullptr && sum != nullptr, "mirror_add: x and sum must point to {} floats of device memory",
           n);
  PS_CHECK(x + n <= sum || sum + n <= x, "mirror_add: sum must not overlap x");
  launch_kernel(mirror_add_kernel, elementwise_grid(n), dim3(kElementwiseBlock), 0, stream, x, n,
                height, width, mirror_y, mirror_x, sum);
}

}  // namespace pillarseg::cuda
