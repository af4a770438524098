// The element type of a tensor (DESIGN.md section 7: the dtype belongs to the tensor, not to op
// or method names): FP32, the two 16-bit float formats of the mixed-precision paths (stored as
// their bits), the integer types of indices, arg-maxes and labels, and the INT8 convolutions'
// quantized weights (DESIGN.md section 10).
#pragma once

#include <array>
#include <cstddef>

namespace pillarseg {

enum class DType { F32, BF16, F16, I32, U8, I8 };

constexpr size_t dtype_bytes(DType dtype) {
  switch (dtype) {
    case DType::F32:
    case DType::I32:
      return 4;
    case DType::BF16:
    case DType::F16:
      return 2;
    case DType::U8:
    case DType::I8:
      return 1;
  }
  return 4;
}

// "f32", "bf16", "f16", "i32", "u8", "i8".
constexpr const char* dtype_name(DType dtype) {
  switch (dtype) {
    case DType::F32:
      return "f32";
    case DType::BF16:
      return "bf16";
    case DType::F16:
      return "f16";
    case DType::I32:
      return "i32";
    case DType::U8:
      return "u8";
    case DType::I8:
      return "i8";
  }
  return "?";
}

constexpr bool is_float16(DType dtype) { return dtype == DType::BF16 || dtype == DType::F16; }

// How an INT8 convolution quantizes its input x, per tensor with r = 1 / scale rounded to FP32:
// q = clamp(round_half_even(x r), -127, 127) (NaN -> 0, the padding 0), or, for an input that is
// never negative, q = clamp(round_half_even(x r), 0, 255): twice the levels over the same range
// (the U-Net's convolution inputs are ReLU outputs, max-pooled, bilinear-upsampled and
// concatenated; calibration says which, engine/model/calibration.hpp).
// And for a 3x3 pad-1 convolution a CPU without AMX may run in the Winograd domain (F(2x2, 3x3),
// engine/cpu/int8_conv.hpp), the scales of its transformed input V = B^T d B, one per tile
// position p (V_p = clamp(round_half_even(V_p / winograd[p]), -127, 127)): calibrated as the
// per-tensor scale is, all zero where the calibration made none (then the direct kernel runs).
struct Int8Input {
  float scale = 0.0f;  // > 0
  bool non_negative = false;
  std::array<float, 16> winograd{};  // > 0 each, or all 0

  bool has_winograd() const { return winograd[0] > 0.0f; }
};

}  // namespace pillarseg
