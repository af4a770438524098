// Point padding (see pad_points.cuh): a grid-stride loop over the capacity's rows; rows below
// M return at once, the others are written as one float4 of NaN (rows are 16 bytes).
#include "kernels/pad_points.cuh"

#include <cstdint>

#include "kernels/common.cuh"
#include "kernels/float4_split.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
static __global__ void __launch_bounds__(kElementwiseBlock)
    pad_points_kernel(const std::int32_t* __restrict__ num_points, std::int64_t capacity,
                      float4* __restrict__ points) {
  const std::int64_t valid = num_points[0] < 0 ? 0 : num_points[0];
  const float nan = __int_as_float(0x7fc00000);
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  for (std::int64_t row = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x; row < capacity;
       row += stride) {
    if (row >= valid) points[row] = make_float4(nan, nan, nan, nan);
  }
}

void pad_points(const std::int32_t* num_points, std::int64_t capacity, float* points,
                cudaStream_t stream) {
  PS_CHECK(capacity >= 0, "pad_points: the capacity must be >= 0 rows, given {}", capacity);
  PS_CHECK(num_points != nullptr && (capacity == 0 || points != nullptr),
           "pad_points: num_points (1 int32) and points ({} x 4 floats) must be device memory",
           capacity);
  PS_CHECK(reinterpret_cast<std::uintptr_t>(points) % 16 == 0,
           "pad_points: points must be 16-byte aligned (rows of 4 floats), given {}",
           static_cast<const void*>(points));
  if (capacity == 0) return;
  launch_kernel(pad_points_kernel, elementwise_grid(capacity),
                dim3(kElementwiseBlock), 0, stream, num_points, capacity,
                reinterpret_cast<float4*>(points));
}

}  // namespace pillarseg::cuda
