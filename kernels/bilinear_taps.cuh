// The taps of bilinear x2 upsampling with align_corners = true along one axis, shared by the FP32
// kernels (upsample_bilinear.cu) and the 16-bit ones (half_ops.cu) so that both weigh the same.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// Output sample d of an axis: (1 - lambda) in[i0] + lambda in[i1].
struct Tap {
  std::int64_t i0;
  std::int64_t i1;
  float w0;  // 1 - lambda
  float w1;  // lambda
};

// The tap of output d of an axis with `in` inputs and out = 2 in outputs: s = d (in - 1) /
// (out - 1) = i0 + remainder / (out - 1), the weights rounded once from the exact fractions.
__device__ __forceinline__ Tap axis_tap(std::int64_t d, std::int64_t in, std::int64_t out) {
  if (in == 1) return Tap{0, 0, 1.0f, 0.0f};
  const std::int64_t numerator = d * (in - 1);
  const std::int64_t i0 = numerator / (out - 1);
  const std::int64_t remainder = numerator - i0 * (out - 1);
  const auto denominator = static_cast<float>(out - 1);
  return Tap{i0, i0 + 1 < in ? i0 + 1 : in - 1,
             static_cast<float>(out - 1 - remainder) / denominator,
             static_cast<float>(remainder) / denominator};
}

}  // namespace pillarseg::cuda
