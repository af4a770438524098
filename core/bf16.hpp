// BF16 bit patterns (the top half of a float32) and float32: exact widening and rounding to
// nearest even; shared by the checkpoints (weights_io/half.hpp) and the CPU's FP32 arithmetic on
// BF16 activations (host/conv2d_winograd.hpp).
#pragma once

#include <bit>
#include <cstdint>

namespace pillarseg {

// float32 -> BF16 bit pattern, round to nearest even on the dropped low 16 bits. Values that
// round past the largest BF16 (about 3.39e38) become Inf.
constexpr std::uint16_t float_to_bf16_bits(float value) {
  const std::uint32_t bits = std::bit_cast<std::uint32_t>(value);
  if ((bits & 0x7FFFFFFFu) > 0x7F800000u) {
    return static_cast<std::uint16_t>((bits >> 16) | 0x0040u);  // NaN: quiet, keeps sign
  }
  const std::uint32_t round_bias = 0x7FFFu + ((bits >> 16) & 1u);
  return static_cast<std::uint16_t>((bits + round_bias) >> 16);
}

// BF16 bit pattern -> float32, exact (BF16 is the top half of a float32).
constexpr float bf16_bits_to_float(std::uint16_t bf16) {
  return std::bit_cast<float>(static_cast<std::uint32_t>(bf16) << 16);
}

}  // namespace pillarseg
