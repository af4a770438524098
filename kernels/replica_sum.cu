// chunks (R, n) -> out (n): the replicas' values added in replica order, one thread per value
// (grid-stride), for floats and doubles; see replica_sum.cuh.
#include "kernels/replica_sum.cuh"

#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kBlock = 256;
constexpr std::int64_t kMaxBlocks = 4096;

}  // namespace

template <class T>
static __global__ void __launch_bounds__(kBlock)
    sum_replica_chunks_kernel(const T* chunks, int replicas, std::int64_t n, T* out) {
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  for (std::int64_t i = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x; i < n; i += stride) {
    T total = chunks[i];
    for (int r = 1; r < replicas; ++r) total += chunks[r * n + i];
    out[i] = total;
  }
}

template <class T>
static void launch_sum_replica_chunks(const T* chunks, int replicas, std::int64_t n, T* out,
                                      cudaStream_t stream) {
  PS_CHECK(replicas >= 1 && n >= 0,
           "sum_replica_chunks: expected replicas >= 1 and n >= 0, given {} and {}", replicas, n);
  if (n == 0) return;
  PS_CHECK(chunks != nullptr && out != nullptr,
           "sum_replica_chunks: chunks ({} x {} values) and out ({} values) must be device memory",
           replicas, n, n);
  const std::int64_t blocks = ceil_div(n, std::int64_t{kBlock});
  launch_kernel(sum_replica_chunks_kernel<T>,
                dim3(static_cast<unsigned>(blocks < kMaxBlocks ? blocks : kMaxBlocks)),
                dim3(kBlock), 0, stream, chunks, replicas, n, out);
}

void sum_replica_chunks(const float* chunks, int replicas, std::int64_t n, float* out,
                        cudaStream_t stream) {
  launch_sum_replica_chunks(chunks, replicas, n, out, stream);
}

void sum_replica_chunks(const double* chunks, int replicas, std::int64_t n, double* out,
                        cudaStream_t stream) {
  launch_sum_replica_chunks(chunks, replicas, n, out, stream);
}

}  // namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE
