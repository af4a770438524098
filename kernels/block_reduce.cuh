// Device helpers for deterministic sums inside a kernel: over the 32 lanes of a warp with
// shuffles, over a whole block through one shared word per warp, over a strided array by one
// warp (the second pass of a two-pass reduction), and the shift of shifted statistics sums. The
// additions happen in an order fixed by the thread indices alone, so the same inputs give the
// same bits on every run (STYLE rule 9); the kernels combine per-block results this way in a
// second pass instead of with atomics. Included by .cu files only; nothing here is a launcher.
#pragma once

#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

inline constexpr int kWarpSize = 32;

// Sum of v over the 32 lanes of a full warp, as a tree of shuffles; lane 0 holds the total.
template <class T>
__device__ __forceinline__ T warp_sum(T v) {
  for (int offset = kWarpSize / 2; offset > 0; offset >>= 1) {
    v += __shfl_down_sync(0xffffffffu, v, offset);
  }
  return v;
}

// Sum of v over the kBlockSize threads of a block (any blockDim shape with that many threads,
// numbered x fastest); thread 0 holds the total. Every thread must call it. Ends with a barrier,
// so a kernel may call it again at once.
template <int kBlockSize, class T>
__device__ __forceinline__ T block_sum(T v) {
  static_assert(kBlockSize % kWarpSize == 0 && kBlockSize <= kWarpSize * kWarpSize,
                "block_sum needs whole warps, at most 32 of them");
  constexpr int kWarps = kBlockSize / kWarpSize;
  __shared__ T warp_totals[kWarps];
  const int thread =
      static_cast<int>(threadIdx.x + blockDim.x * (threadIdx.y + blockDim.y * threadIdx.z));
  const int lane = thread % kWarpSize;
  const int warp = thread / kWarpSize;
  v = warp_sum(v);
  if (lane == 0) warp_totals[warp] = v;
  __syncthreads();
  if (warp == 0) {
    v = lane < kWarps ? warp_totals[lane] : T(0);
    v = warp_sum(v);
  }
  __syncthreads();
  return v;
}

// The value a shifted sum of a channel is taken relative to, sum (v - shift) and
// sum (v - shift)^2 (the variance then has no cancellation for a large mean against a small
// spread): the channel's first value, or 0 if that is not finite (a shift of Inf or NaN would
// turn every sum into NaN).
__device__ __forceinline__ double sum_shift(float first) {
  const bool finite = first - first == 0.0f;  // Inf - Inf and NaN - NaN are NaN
  return finite ? static_cast<double>(first) : 0.0;
}

// Sum of values[0], values[stride], ... values[(count - 1) * stride] by the 32 lanes of a warp
// (each lane a strided share, then a shuffle tree); every lane of the warp must call it and lane 0
// holds the total. The second pass of the kernels' two-pass reductions.
__device__ __forceinline__ double warp_sum_strided(const double* values, long long count,
                                                   long long stride, int lane) {
  double sum = 0.0;
  for (long long i = lane; i < count; i += kWarpSize) sum += values[i * stride];
  return warp_sum(sum);
}

}  // namespace pillarseg::cuda
