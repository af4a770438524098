// Sum of squares of a float array in two passes (see reduce.cuh). Pass 1: a grid of B blocks
// (B depends on n only, at most kSumOfSquaresPartials) walks x with a grid-stride loop, each
// thread summing its elements' squares in double, each block summing its threads with warp
// shuffles and shared memory into partials[b]. Pass 2: one block sums the B partials the same way.
#include "kernels/reduce.cuh"

#include <algorithm>
#include <cstdint>

#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kBlockSize = 256;
constexpr int kWarps = kBlockSize / 32;
// Elements per thread before pass 1 adds another block: enough work per thread to hide latency.
constexpr std::int64_t kElementsPerThread = 8;

}  // namespace

// Sum of v over the 32 lanes of a full warp, in a fixed order; lane 0 holds the total.
static __device__ __forceinline__ double warp_sum(double v) {
  for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_down_sync(0xffffffffu, v, offset);
  return v;
}

// Sum of v over a block of kBlockSize threads, in a fixed order; thread 0 holds the total.
static __device__ __forceinline__ double block_sum(double v) {
  __shared__ double warp_totals[kWarps];
  const int lane = static_cast<int>(threadIdx.x % 32);
  const int warp = static_cast<int>(threadIdx.x / 32);
  v = warp_sum(v);
  if (lane == 0) warp_totals[warp] = v;
  __syncthreads();
  if (warp == 0) {
    v = lane < kWarps ? warp_totals[lane] : 0.0;
    v = warp_sum(v);
  }
  return v;
}

// x (n) -> partials (gridDim.x): partials[b] = sum of x[i]^2 over the elements block b visits.
static __global__ void __launch_bounds__(kBlockSize)
    sum_of_squares_partials_kernel(const float* x, std::int64_t n, double* partials) {
  double sum = 0.0;
  const std::int64_t stride = std::int64_t{gridDim.x} * kBlockSize;
  for (std::int64_t i = std::int64_t{blockIdx.x} * kBlockSize + threadIdx.x; i < n; i += stride) {
    const double v = x[i];
    sum += v * v;
  }
  sum = block_sum(sum);
  if (threadIdx.x == 0) partials[blockIdx.x] = sum;
}

// partials (count) -> *result = their sum; one block.
static __global__ void __launch_bounds__(kBlockSize)
    sum_partials_kernel(const double* partials, int count, double* result) {
  double sum = 0.0;
  for (int i = static_cast<int>(threadIdx.x); i < count; i += kBlockSize) sum += partials[i];
  sum = block_sum(sum);
  if (threadIdx.x == 0) *result = sum;
}

void sum_of_squares(const float* x, std::int64_t n, double* partials, double* result,
                    cudaStream_t stream) {
  PS_CHECK(n >= 0, "sum_of_squares: n = {}; expected a number of elements >= 0", n);
  PS_CHECK(n == 0 || x != nullptr, "sum_of_squares: x is null with n = {} elements", n);
  PS_CHECK(partials != nullptr && result != nullptr,
           "sum_of_squares: partials ({} doubles of scratch) and result (1 double) must be device "
           "memory, got "
           "partials = {}, result = {}",
           kSumOfSquaresPartials, static_cast<const void*>(partials),
           static_cast<const void*>(result));
  const std::int64_t blocks = std::clamp<std::int64_t>(ceil_div(n, kBlockSize * kElementsPerThread),
                                                       1, kSumOfSquaresPartials);
  launch_kernel(sum_of_squares_partials_kernel, dim3(static_cast<unsigned>(blocks)),
                dim3(kBlockSize), 0, stream, x, n, partials);
  launch_kernel(sum_partials_kernel, dim3(1), dim3(kBlockSize), 0, stream, partials,
                static_cast<int>(blocks), result);
}

}  // namespace pillarseg::cuda
