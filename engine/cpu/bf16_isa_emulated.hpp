// An exact scalar model of the AVX-512 instructions the BF16 micro-kernel uses
// (bf16_microkernel.hpp), after the Intel SDM's pseudo-code, so that the micro-kernel runs and
// is tested on every CPU:
//   VDPBF16PS     acc[j] = fma(a[2j + 1], b[2j + 1], acc[j]), then fma(a[2j], b[2j], acc[j]):
//                 each step one FP32 rounding to nearest even, denormal inputs (the BF16 values
//                 and the accumulator) read as zero and denormal results flushed to zero;
//   VCVTNEPS2BF16 FP32 -> BF16 to nearest even; zero and denormal inputs give a signed zero,
//                 infinities stay, NaNs stay NaN with the quiet bit set;
//   masked loads  (vmovdqu16 with a zeroing mask) read only the lanes the mask names;
//   the rest are plain moves, shifts and masks of words, FP32 adds and subtractions, max(v, 0) (NaN
//   -> 0 as VMAXPS(v, 0) gives) and stores.
// The AVX-512 implementation of the same interface is in bf16_conv_avx512.cpp. And of the AMX
// tile instructions the Winograd products use (bf16_amx.hpp), EmulatedAmxTiles:
//   TDPBF16PS     C[m][n] += A[m].bf16[2k] B[k].bf16[2n], then the odd elements, for k in order,
//                 each an FMA with one rounding to nearest even, denormals as in VDPBF16PS;
//   TILELOADD, TILESTORED, TILEZERO on full tiles (16 rows of 64 bytes), one tile file a thread.
#pragma once

#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>

namespace pillarseg::cpu {

struct EmulatedBf16Isa {
  struct Acc {
    float v[16];
  };
  struct Pair {
    std::uint16_t v[32];
  };

  static float flush_denormal(float x) {
    return std::fpclassify(x) == FP_SUBNORMAL ? std::copysign(0.0f, x) : x;
  }
  static float bf16_to_float(std::uint16_t bits) {
    return flush_denormal(std::bit_cast<float>(static_cast<std::uint32_t>(bits) << 16));
  }
  static std::uint16_t float_to_bf16(float x) {
    const std::uint32_t bits = std::bit_cast<std::uint32_t>(x);
    const std::uint32_t exponent = bits & 0x7F800000u, mantissa = bits & 0x007FFFFFu;
    if (exponent == 0) return static_cast<std::uint16_t>((bits >> 16) & 0x8000u);
    if (exponent == 0x7F800000u) {
      return static_cast<std::uint16_t>((bits >> 16) | (mantissa != 0 ? 0x0040u : 0u));
    }
    return static_cast<std::uint16_t>((bits + 0x7FFFu + ((bits >> 16) & 1u)) >> 16);
  }

  static Acc zero() { return Acc{}; }
  // Lane i: (base[first + i] where bit i of first_mask is set, else 0, the same for second).
  static Pair load_pairs(const std::uint16_t* base, std::int64_t first, std::uint32_t first_mask,
                         std::int64_t second, std::uint32_t second_mask) {
    Pair a{};
    for (int i = 0; i < 16; ++i) {
      if ((first_mask >> i) & 1u) a.v[2 * i] = base[first + i];
      if ((second_mask >> i) & 1u) a.v[2 * i + 1] = base[second + i];
    }
    return a;
  }
  // The 32 words at `words` (16 pairs), a plain 64-byte load.
  static Pair load_words(const std::uint16_t* words) {
    Pair a;
    for (int i = 0; i < 32; ++i) a.v[i] = words[i];
    return a;
  }
  // Word i: base[index + i] where bit i of the 32-lane mask is set, else 0.
  static Pair load_words_masked(const std::uint16_t* base, std::int64_t index, std::uint32_t mask) {
    Pair a{};
    for (int i = 0; i < 32; ++i)
      if ((mask >> i) & 1u) a.v[i] = base[index + i];
    return a;
  }
  // Lane i: the BF16 word 2 i (even) or 2 i + 1 (odd) as FP32 (a shift or a mask of dword i).
  static Acc even_words(const Pair& a) {
    Acc r;
    for (int i = 0; i < 16; ++i)
      r.v[i] = std::bit_cast<float>(static_cast<std::uint32_t>(a.v[2 * i]) << 16);
    return r;
  }
  static Acc odd_words(const Pair& a) {
    Acc r;
    for (int i = 0; i < 16; ++i)
      r.v[i] = std::bit_cast<float>(static_cast<std::uint32_t>(a.v[2 * i + 1]) << 16);
    return r;
  }
  static Acc load_f32(const float* y) {
    Acc r;
    for (int i = 0; i < 16; ++i) r.v[i] = y[i];
    return r;
  }
  static Acc add(const Acc& a, const Acc& b) {
    Acc r;
    for (int i = 0; i < 16; ++i) r.v[i] = a.v[i] + b.v[i];
    return r;
  }
  static Acc sub(const Acc& a, const Acc& b) {
    Acc r;
    for (int i = 0; i < 16; ++i) r.v[i] = a.v[i] - b.v[i];
    return r;
  }
  static Pair broadcast_pair(const std::uint16_t* two) {
    Pair a;
    for (int i = 0; i < 16; ++i) a.v[2 * i] = two[0], a.v[2 * i + 1] = two[1];
    return a;
  }
  static Acc dot(Acc acc, const Pair& a, const Pair& b) {
    for (int j = 0; j < 16; ++j) {
      float t = flush_denormal(acc.v[j]);
      t = flush_denormal(std::fma(bf16_to_float(a.v[2 * j + 1]), bf16_to_float(b.v[2 * j + 1]), t));
      t = flush_denormal(std::fma(bf16_to_float(a.v[2 * j]), bf16_to_float(b.v[2 * j]), t));
      acc.v[j] = t;
    }
    return acc;
  }
  static Acc bias_act(Acc acc, float bias, bool relu) {
    for (float& v : acc.v) {
      v += bias;
      if (relu) v = v > 0.0f ? v : 0.0f;
    }
    return acc;
  }
  static void store_f32(float* y, const Acc& acc, std::uint32_t mask) {
    for (int i = 0; i < 16; ++i)
      if ((mask >> i) & 1u) y[i] = acc.v[i];
  }
  static void store_bf16(std::uint16_t* y, const Acc& acc, std::uint32_t mask) {
    for (int i = 0; i < 16; ++i)
      if ((mask >> i) & 1u) y[i] = float_to_bf16(acc.v[i]);
  }
  // y[2 i] = even[i], y[2 i + 1] = odd[i], for the bits of the 32-lane mask.
  static void store_f32_interleaved(float* y, const Acc& even, const Acc& odd, std::uint32_t mask) {
    for (int i = 0; i < 32; ++i)
      if ((mask >> i) & 1u) y[i] = (i % 2 == 0 ? even : odd).v[i / 2];
  }
  static void store_bf16_interleaved(std::uint16_t* y, const Acc& even, const Acc& odd,
                                     std::uint32_t mask) {
    for (int i = 0; i < 32; ++i)
      if ((mask >> i) & 1u) y[i] = float_to_bf16((i % 2 == 0 ? even : odd).v[i / 2]);
  }
};

// The tile instructions (see above), the interface of AmxTiles in bf16_conv_avx512.cpp.
struct EmulatedAmxTiles {
  struct Tile {
    std::uint32_t d[16][16];  // rows of 16 dwords: FP32 values or BF16 pairs
  };
  static Tile* file() {
    thread_local Tile tiles[8];
    return tiles;
  }
  template <class Config>
  static void configure(const Config&) {}
  static void release() {}
  template <int T>
  static void zero() {
    std::memset(file()[T].d, 0, sizeof(Tile));
  }
  template <int T>
  static void load(const void* base, std::int64_t stride_bytes) {
    for (int r = 0; r < 16; ++r)
      std::memcpy(file()[T].d[r], static_cast<const std::uint8_t*>(base) + r * stride_bytes, 64);
  }
  template <int T>
  static void store(void* base, std::int64_t stride_bytes) {
    for (int r = 0; r < 16; ++r)
      std::memcpy(static_cast<std::uint8_t*>(base) + r * stride_bytes, file()[T].d[r], 64);
  }
  static float fp32(std::uint32_t bits) {
    float f;
    std::memcpy(&f, &bits, sizeof(f));
    return f;
  }
  // C[m][n] += sum_k A[m].bf16[2k] B[k].bf16[2n] + A[m].bf16[2k + 1] B[k].bf16[2n + 1], k in order.
  template <int C, int A, int B>
  static void dot() {
    Tile& c = file()[C];
    const Tile& a = file()[A];
    const Tile& b = file()[B];
    for (int m = 0; m < 16; ++m) {
      for (int n = 0; n < 16; ++n) {
        float acc = EmulatedBf16Isa::flush_denormal(fp32(c.d[m][n]));
        for (int k = 0; k < 16; ++k) {
          for (int half = 0; half < 2; ++half) {
            const int shift = 16 * half;
            const float x =
                EmulatedBf16Isa::bf16_to_float(static_cast<std::uint16_t>(a.d[m][k] >> shift));
            const float y =
                EmulatedBf16Isa::bf16_to_float(static_cast<std::uint16_t>(b.d[k][n] >> shift));
            acc = EmulatedBf16Isa::flush_denormal(std::fma(x, y, acc));
          }
        }
        std::memcpy(&c.d[m][n], &acc, sizeof(acc));
      }
    }
  }
};

}  // namespace pillarseg::cpu
