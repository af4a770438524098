// Elementwise and copy ops of the CUDA backend on flat float arrays and channel bands:
//   add_inplace      a (n) += b (n)                  (the gradient of a tensor used twice);
//   scale            x (n) *= factor                 (gradient-norm clipping);
//   copy_channels    x (B, Cx, S) -> channels [channel0, channel0 + Cx) of y (B, Cy, S);
//   extract_channels channels [channel0, channel0 + Cx) of y (B, Cy, S) -> x (B, Cx, S),
// with S = H * W (the input streams concatenated along channels, and their gradients).
// Pure data movement or one rounding per element: results are exact and deterministic.
// Pointers are device memory; the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// a (n) += b (n). a and b do not overlap, or are the same array.
void add_inplace(float* a, const float* b, std::int64_t n, cudaStream_t stream);

// x (n) *= factor.
void scale(float* x, float factor, std::int64_t n, cudaStream_t stream);

// A band of channels inside a wider tensor: `batch` items of `channels` planes of `inner` values
// (the narrow tensor), placed at channel `channel0` of items with `wide_channels` planes.
struct ChannelBand {
  std::int64_t batch = 0;
  std::int64_t channels = 0;       // Cx
  std::int64_t inner = 0;          // S = H * W
  std::int64_t wide_channels = 0;  // Cy
  std::int64_t channel0 = 0;
};

// x (B, Cx, S) -> y (B, Cy, S) channels [channel0, channel0 + Cx); the other channels of y are
// untouched. x and y do not overlap.
void copy_channels(const float* x, const ChannelBand& band, float* y, cudaStream_t stream);

// y (B, Cy, S) channels [channel0, channel0 + Cx) -> x (B, Cx, S). x and y do not overlap.
void extract_channels(const float* y, const ChannelBand& band, float* x, cudaStream_t stream);

}  // namespace pillarseg::cuda
