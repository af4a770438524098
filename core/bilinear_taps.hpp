// The taps of bilinear x2 upsampling with align_corners = true along one axis: the one function
// the host reference (host/upsample_bilinear), the FP32 and 16-bit kernels (kernels/
// upsample_bilinear.cu, half_ops.cu) and the CPU's 16-bit path (engine/cpu/bf16_conv.cpp) weigh
// by, so that all of them weigh the same.
//
// Output sample d of an axis with `in` inputs and out = 2 in outputs reads the source coordinate
// s = d (in - 1) / (out - 1) = i0 + r / (out - 1) (r the remainder of the exact integer division):
// y = w0 in[i0] + w1 in[i1] with w1 = r / (out - 1) and w0 = (out - 1 - r) / (out - 1), each
// rounded once from the exact fraction in T (float for the kernels and the FP32 reference;
// double for the double reference).
#pragma once

#include <cstdint>

#include "core/host_device.hpp"

namespace pillarseg {

template <class T>
struct BilinearTap {
  std::int64_t i0;
  std::int64_t i1;
  T w0;  // 1 - lambda
  T w1;  // lambda
};

template <class T>
PILLARSEG_HOST_DEVICE inline BilinearTap<T> bilinear_tap(std::int64_t d, std::int64_t in, std::int64_t out) {
  if (in == 1 || out == 1) return BilinearTap<T>{0, 0, T(1), T(0)};
  const std::int64_t numerator = d * (in - 1);
  const std::int64_t i0 = numerator / (out - 1);
  const std::int64_t remainder = numerator - i0 * (out - 1);
  const auto denominator = static_cast<T>(out - 1);
  return BilinearTap<T>{i0, i0 + 1 < in ? i0 + 1 : in - 1, static_cast<T>(out - 1 - remainder) / denominator,
                        static_cast<T>(remainder) / denominator};
}

}  // namespace pillarseg
