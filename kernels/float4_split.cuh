// Float4Split: a flat array of n floats, [0, n), as work items for memory-bound elementwise
// kernels that move four floats per load and store (float4) wherever every array involved shares
// one 16-byte alignment: a scalar head of up to 3 elements reaches the boundary, a float4 body
// follows, and a scalar tail of up to 3 elements ends. Arrays with different alignments take the
// scalar path for every element. Items below `vectors` are float4s (element head + 4 * item),
// the others single elements (scalar_element). Included by .cu files only.
#pragma once

#include <algorithm>
#include <cstdint>
#include <initializer_list>

#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

struct Float4Split {
  std::int64_t head = 0;
  std::int64_t vectors = 0;
  std::int64_t tail = 0;
  __host__ __device__ std::int64_t items() const { return vectors + head + tail; }
};

// The split of [0, n) for arrays starting at `pointers` (all of n floats).
inline Float4Split split_for_float4(std::int64_t n, std::initializer_list<const float*> pointers) {
  const auto misalignment = [](const float* p) { return reinterpret_cast<std::uintptr_t>(p) % 16; };
  const std::uintptr_t shared_misalignment = misalignment(*pointers.begin());
  for (const float* p : pointers) {
    if (misalignment(p) != shared_misalignment) return Float4Split{n, 0, 0};
  }
  const std::int64_t head =
      std::min<std::int64_t>(n, static_cast<std::int64_t>((16 - shared_misalignment) % 16 / 4));
  const std::int64_t vectors = (n - head) / 4;
  return Float4Split{head, vectors, n - head - 4 * vectors};
}

// The element of scalar work item s (0 <= s < head + tail).
__device__ __forceinline__ std::int64_t scalar_element(const Float4Split& split, std::int64_t s) {
  return s < split.head ? s : split.head + 4 * split.vectors + (s - split.head);
}

// A grid of at most max_blocks blocks of block_size threads for a grid-stride loop over `items`
// (at least one block).
inline dim3 grid_stride_blocks(std::int64_t items, int block_size, std::int64_t max_blocks) {
  return dim3(static_cast<unsigned>(
      std::clamp<std::int64_t>(ceil_div(items, std::int64_t{block_size}), 1, max_blocks)));
}

// The memory-bound elementwise kernels' grid-stride loops: blocks of kElementwiseBlock threads,
// at most kElementwiseMaxBlocks of them (4096 blocks of 256 threads fill any current GPU).
inline constexpr int kElementwiseBlock = 256;
inline constexpr std::int64_t kElementwiseMaxBlocks = 4096;
inline dim3 elementwise_grid(std::int64_t items) {
  return grid_stride_blocks(items, kElementwiseBlock, kElementwiseMaxBlocks);
}

}  // namespace pillarseg::cuda
