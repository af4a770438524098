// Device helpers for prefix sums of integers inside a kernel: over the 32 lanes of a warp with
// shuffles, and over the threads of a block through one shared word per warp. Integer sums are
// exact, so the results do not depend on any scheduling (STYLE rule 9); the data-pipeline kernels
// (kernels/pillar_gather.cu, kernels/raywalk.cu) build their device-wide scans from these.
// Included by .cu files only; nothing here is a launcher.
#pragma once

#include "kernels/block_reduce.cuh"
#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// Inclusive prefix sum of v over the lanes of a full warp: lane l gets v(0) + ... + v(l).
template <class T>
__device__ __forceinline__ T warp_inclusive_scan(T v, int lane) {
  for (int offset = 1; offset < kWarpSize; offset <<= 1) {
    const T from_below = __shfl_up_sync(0xffffffffu, v, offset);
    if (lane >= offset) v += from_below;
  }
  return v;
}

// Exclusive prefix sum of v over the kBlockSize threads of a one-dimensional block: thread t gets
// v(0) + ... + v(t - 1), and *block_total (every thread) the sum over the block. Every thread must
// call it. Ends with a barrier, so a kernel may call it again at once.
template <int kBlockSize, class T>
__device__ __forceinline__ T block_exclusive_scan(T v, T* block_total) {
  static_assert(kBlockSize % kWarpSize == 0 && kBlockSize <= kWarpSize * kWarpSize,
                "block_exclusive_scan needs whole warps, at most 32 of them");
  constexpr int kWarps = kBlockSize / kWarpSize;
  __shared__ T warp_totals[kWarps];
  const int thread = static_cast<int>(threadIdx.x);
  const int lane = thread % kWarpSize;
  const int warp = thread / kWarpSize;
  const T inclusive = warp_inclusive_scan(v, lane);
  if (lane == kWarpSize - 1) warp_totals[warp] = inclusive;
  __syncthreads();
  if (warp == 0) {
    const T total = lane < kWarps ? warp_totals[lane] : T(0);
    const T scanned = warp_inclusive_scan(total, lane);
    if (lane < kWarps) warp_totals[lane] = scanned;  // inclusive sums of the warp totals
  }
  __syncthreads();
  const T before_warp = warp > 0 ? warp_totals[warp - 1] : T(0);
  *block_total = warp_totals[kWarps - 1];
  __syncthreads();
  return before_warp + inclusive - v;
}

}  // namespace pillarseg::cuda
