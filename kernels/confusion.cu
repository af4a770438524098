// Confusion matrix (see confusion.cuh): each block counts a grid-stride share of the cells into a
// shared-memory histogram of 12 x 12 + 1 (invalid) uint32 bins, then adds its non-zero bins to
// the int64 matrix in global memory with one atomic each: 145 global atomics per block instead
// of one per cell.
#include "kernels/confusion.cuh"

#include <algorithm>
#include <cstdint>

#include "core/classes.hpp"
#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kBlockSize = 256;
constexpr int kMaxBlocks = 1024;
constexpr int kClasses = kNumClasses;
constexpr int kBins = kClasses * kClasses + 1;  // the last bin counts invalid cells
constexpr int kInvalidBin = kClasses * kClasses;
// A block counts at most this many cells (so that a uint32 bin cannot overflow).
constexpr std::int64_t kMaxCellsPerBlock = std::int64_t{1} << 31;

static_assert(sizeof(unsigned long long) == sizeof(std::int64_t),
              "the int64 matrix is updated with 64-bit unsigned atomics");

}  // namespace

// The bin of one cell: row-major (truth - 1, predicted - 1), kInvalidBin, or -1 (not counted).
static __device__ __forceinline__ int bin_of(unsigned truth, unsigned predicted, bool masked_out) {
  if (truth == 0 || masked_out) return -1;
  if (truth > kClasses || predicted < 1 || predicted > kClasses) return kInvalidBin;
  return static_cast<int>((truth - 1) * kClasses + (predicted - 1));
}

static __global__ void __launch_bounds__(kBlockSize)
    confusion_kernel(const std::uint8_t* __restrict__ truth,
                     const std::uint8_t* __restrict__ predicted,
                     const std::uint8_t* __restrict__ mask, std::int64_t n,
                     unsigned long long* __restrict__ confusion,
                     unsigned long long* __restrict__ invalid_cells) {
  __shared__ unsigned int bins[kBins];
  for (int b = static_cast<int>(threadIdx.x); b < kBins; b += kBlockSize) bins[b] = 0;
  __syncthreads();
  const std::int64_t stride = std::int64_t{gridDim.x} * kBlockSize;
  for (std::int64_t i = std::int64_t{blockIdx.x} * kBlockSize + threadIdx.x; i < n; i += stride) {
    const int bin = bin_of(truth[i], predicted[i], mask != nullptr && mask[i] == 0);
    if (bin >= 0) atomicAdd(bins + bin, 1u);
  }
  __syncthreads();
  for (int b = static_cast<int>(threadIdx.x); b < kBins; b += kBlockSize) {
    const unsigned int value = bins[b];
    if (value == 0) continue;
    atomicAdd(b == kInvalidBin ? invalid_cells : confusion + b,
              static_cast<unsigned long long>(value));
  }
}

void confusion_accumulate(const std::uint8_t* truth, const std::uint8_t* predicted,
                          const std::uint8_t* mask, std::int64_t n, std::int64_t* confusion,
                          std::uint64_t* invalid_cells, cudaStream_t stream) {
  constexpr const char* kOp = "confusion_accumulate";
  PS_CHECK(n >= 0, "{}: expected n >= 0 cells, given {}", kOp, n);
  PS_CHECK(confusion != nullptr && invalid_cells != nullptr,
           "{}: confusion ({} x {} int64) and invalid_cells (1 uint64) must be device memory", kOp,
           kClasses, kClasses);
  if (n == 0) return;
  PS_CHECK(truth != nullptr && predicted != nullptr,
           "{}: truth and predicted must point to {} uint8 each of device memory", kOp, n);
  const std::int64_t blocks = std::max<std::int64_t>(
      std::min<std::int64_t>(ceil_div(n, std::int64_t{kBlockSize} * 16), kMaxBlocks),
      ceil_div(n, kMaxCellsPerBlock));
  launch_kernel(confusion_kernel, dim3(static_cast<unsigned>(blocks)), dim3(kBlockSize), 0, stream,
                truth, predicted, mask, n, reinterpret_cast<unsigned long long*>(confusion),
                reinterpret_cast<unsigned long long*>(invalid_cells));
}

}  // namespace pillarseg::cuda
