// Exact conversions between float32 and the 16-bit float formats stored in checkpoints:
// IEEE binary16 (F16: 1 sign, 5 exponent, 10 mantissa bits) and bfloat16 (BF16: 1 sign,
// 8 exponent, 7 mantissa bits, the top half of a float32). Widening to float is exact;
// narrowing rounds to nearest, ties to even, as IEEE 754 and PyTorch's .half()/.bfloat16() do.
// Subnormals are produced and read exactly, overflow gives +-Inf, NaN stays a (quiet) NaN
// with the same sign.
#pragma once

#include <bit>
#include <cstdint>

#include "core/bf16.hpp"

namespace pillarseg::weights {

// float32 -> F16 bit pattern, round to nearest even. |x| >= 65520 (the midpoint between the
// largest F16, 65504, and 2^16) becomes Inf.
constexpr uint16_t float_to_f16_bits(float value) {
  const uint32_t bits = std::bit_cast<uint32_t>(value);
  const auto sign = static_cast<uint16_t>((bits >> 16) & 0x8000u);
  const uint32_t magnitude = bits & 0x7FFFFFFFu;
  if (magnitude >= 0x7F800000u) {
    if (magnitude == 0x7F800000u) return sign | 0x7C00u;
    // NaN: keep the top payload bits and set the quiet bit, so that the payload never
    // truncates to zero (which would turn the NaN into an Inf).
    return static_cast<uint16_t>(sign | 0x7E00u | ((magnitude >> 13) & 0x03FFu));
  }
  const int exponent = static_cast<int>(magnitude >> 23) - 127;  // unbiased
  if (exponent > 15) return sign | 0x7C00u;                      // >= 2^16: overflow
  if (exponent >= -14) {
    // Normal F16: rebias the exponent, keep 10 of the 23 mantissa bits, round the other 13.
    // A carry out of the mantissa correctly bumps the exponent (up to Inf at 0x7C00).
    const uint32_t mantissa = magnitude & 0x007FFFFFu;
    uint32_t half = (static_cast<uint32_t>(exponent + 15) << 10) | (mantissa >> 13);
    const uint32_t rest = mantissa & 0x1FFFu;
    if (rest > 0x1000u || (rest == 0x1000u && (half & 1u))) ++half;
    return static_cast<uint16_t>(sign | half);
  }
  // Below 2^-25 everything rounds to zero (float subnormals included); exactly 2^-25 is a tie
  // between 0 and the smallest subnormal 2^-24 and goes to the even one, 0.
  if (exponent < -25) return sign;
  // F16 subnormal: value = m * 2^-24 with m = significand * 2^(exponent + 1), 24-bit
  // significand, so m is the significand shifted right by -(exponent + 1) = 14..24 bits.
  const uint32_t significand = (magnitude & 0x007FFFFFu) | 0x00800000u;
  const int shift = -exponent - 1;
  uint32_t half = significand >> shift;
  const uint32_t rest = significand & ((1u << shift) - 1u);
  const uint32_t midpoint = 1u << (shift - 1);
  if (rest > midpoint || (rest == midpoint && (half & 1u))) ++half;  // may carry into 2^-14
  return static_cast<uint16_t>(sign | half);
}

// F16 bit pattern -> float32, exact.
constexpr float f16_bits_to_float(uint16_t half) {
  const uint32_t sign = static_cast<uint32_t>(half & 0x8000u) << 16;
  const uint32_t exponent = (half >> 10) & 0x1Fu;
  uint32_t mantissa = half & 0x03FFu;
  if (exponent == 0x1Fu) return std::bit_cast<float>(sign | 0x7F800000u | (mantissa << 13));
  if (exponent != 0) {
    return std::bit_cast<float>(sign | ((exponent + 112u) << 23) | (mantissa << 13));
  }
  if (mantissa == 0) return std::bit_cast<float>(sign);
  // Subnormal m * 2^-24: normalise so that the leading one becomes the implicit bit.
  uint32_t float_exponent = 113;  // biased exponent of 2^-14, the scale of mantissa bit 10
  while ((mantissa & 0x0400u) == 0) {
    mantissa <<= 1;
    --float_exponent;
  }
  return std::bit_cast<float>(sign | (float_exponent << 23) | ((mantissa & 0x03FFu) << 13));
}

// BF16: core/bf16.hpp (host/ rounds activations with the same functions).
using pillarseg::bf16_bits_to_float;
using pillarseg::float_to_bf16_bits;

}  // namespace pillarseg::weights
