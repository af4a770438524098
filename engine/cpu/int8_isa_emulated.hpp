// An exact scalar model of the AVX-512 instructions the INT8 micro-kernel uses
// (int8_microkernel.hpp), after the Intel SDM's pseudo-code, so that it runs and is tested on
// every CPU:
//   VPDPBUSD     acc.dword[j] += zext(a.byte[4j + i]) * sext(b.byte[4j + i]) for i = 0..3, in
//                32-bit two's complement arithmetic: wraps, no saturation (VPDPBUSDS saturates);
//   VCVTDQ2PS    int32 -> FP32, rounded to nearest even;
//   VFMADD       one rounding;  VMAXPS(v, 0)  NaN -> 0;
//   VCVTPS2DQ    {rn-sae}: FP32 -> int32, nearest even (the values are clamped to +-127, or to
//                0..255 for a non-negative input, first);
//   the BF16 rounding of the outputs in integer operations (weights::float_to_bf16_bits: nearest
//   even, NaN kept quiet, no flushing), masked loads and stores reading or writing only the lanes
//   the mask names; for the Winograd transforms (int8_winograd.hpp) the 16-bit integer input
//   transform: the input's even and odd columns (VPERMT2PS of FP32 pairs of vectors, or the words
//   of BF16 pairs as FP32: VPSLLD, VPANDD) to int16 (VCVTPS2DQ {rn-sae} of a clamped product,
//   VPACKSSDW), VPADDW, VPSUBW, VPMULHRSW, VPACKSSWB, VPMAXSB and the unpacks that interleave four
//   channels' bytes; and the output transform's FP32 adds and subtractions (VADDPS, VSUBPS: one
//   rounding each).
// And of the AMX-INT8 tile instructions (int8_amx.hpp), EmulatedAmxInt8Tiles:
//   TDPBSUD      C[m].dword[n] += sext(A[m].byte[4k + i]) * zext(B[k].byte[4n + i]) for k <
//                16, i < 4, wrapping like VPDPBUSD (signed A, unsigned B: the operand roles of
//                TDPBUSD swapped, see int8_amx.hpp);
//   TILELOADD, TILESTORED, TILEZERO on full tiles (16 rows of 64 bytes), one tile file a thread.
// The AVX-512 implementation of the same interfaces is in int8_conv_avx512.cpp.
#pragma once

#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>

namespace pillarseg::cpu {

struct EmulatedVnniIsa {
  struct Acc {
    std::int32_t v[16];
  };
  struct Bytes {
    std::uint8_t v[64];
  };
  struct F {
    float v[16];
  };

  static std::int32_t wrap(std::int64_t v) {
    return static_cast<std::int32_t>(static_cast<std::uint32_t>(static_cast<std::uint64_t>(v)));
  }
  static std::uint16_t bf16_bits(float x) {
    const std::uint32_t bits = std::bit_cast<std::uint32_t>(x);
    if ((bits & 0x7FFFFFFFu) > 0x7F800000u) return static_cast<std::uint16_t>((bits >> 16) | 0x40u);
    return static_cast<std::uint16_t>((bits + 0x7FFFu + ((bits >> 16) & 1u)) >> 16);
  }

  static Acc zero() { return Acc{}; }
  static Bytes load(const std::uint8_t* p) {
    Bytes b;
    std::memcpy(b.v, p, 64);
    return b;
  }
  // The 4 bytes at w in every dword.
  static Bytes broadcast4(const std::int8_t* w) {
    Bytes b;
    for (int j = 0; j < 16; ++j) std::memcpy(b.v + 4 * j, w, 4);
    return b;
  }
  // VPDPBUSD acc, a (unsigned), b (signed).
  static Acc dot(Acc acc, const Bytes& a, const Bytes& b) {
    for (int j = 0; j < 16; ++j) {
      std::int64_t sum = acc.v[j];
      for (int i = 0; i < 4; ++i)
        sum += static_cast<std::int64_t>(a.v[4 * j + i]) * static_cast<std::int8_t>(b.v[4 * j + i]);
      acc.v[j] = wrap(sum);
    }
    return acc;
  }
  static Acc load_acc(const std::int32_t* p) {
    Acc a;
    std::memcpy(a.v, p, sizeof(a.v));
    return a;
  }
  // act(fma(float(acc - comp), scale, bias)).
  static F epilogue(const Acc& acc, std::int32_t comp, float scale, float bias, bool relu) {
    F f;
    for (int j = 0; j < 16; ++j) {
      const auto v = static_cast<float>(wrap(static_cast<std::int64_t>(acc.v[j]) - comp));
      const float y = std::fma(v, scale, bias);
      f.v[j] = relu ? (y > 0.0f ? y : 0.0f) : y;
    }
    return f;
  }
  static void store_f32(float* y, const F& f, std::uint32_t mask) {
    for (int i = 0; i < 16; ++i)
      if ((mask >> i) & 1u) y[i] = f.v[i];
  }
  static void store_bf16(std::uint16_t* y, const F& f, std::uint32_t mask) {
    for (int i = 0; i < 16; ++i)
      if ((mask >> i) & 1u) y[i] = bf16_bits(f.v[i]);
  }
  // y[2 i] = even[i], y[2 i + 1] = odd[i] for the bits of the 32-lane mask.
  static void store_f32_interleaved(float* y, const F& even, const F& odd, std::uint32_t mask) {
    for (int i = 0; i < 32; ++i)
      if ((mask >> i) & 1u) y[i] = (i % 2 == 0 ? even : odd).v[i / 2];
  }
  static void store_bf16_interleaved(std::uint16_t* y, const F& even, const F& odd,
                                     std::uint32_t mask) {
    for (int i = 0; i < 32; ++i)
      if ((mask >> i) & 1u) y[i] = bf16_bits((i % 2 == 0 ? even : odd).v[i / 2]);
  }

  // Quantization: lanes the mask leaves out read as 0.
  static F load_f32(const float* x, std::uint32_t mask) {
    F f{};
    for (int i = 0; i < 16; ++i)
      if ((mask >> i) & 1u) f.v[i] = x[i];
    return f;
  }
  static F load_bf16(const std::uint16_t* x, std::uint32_t mask) {
    F f{};
    for (int i = 0; i < 16; ++i)
      if ((mask >> i) & 1u) f.v[i] = std::bit_cast<float>(static_cast<std::uint32_t>(x[i]) << 16);
    return f;
  }
  // u = clamp(round_half_even(x * reciprocal), -127, 127) + 128, NaN -> 128.
  static Acc quantize_u8(const F& x, float reciprocal) {
    Acc a;
    for (int i = 0; i < 16; ++i) {
      float r = x.v[i] * reciprocal;
      if (std::isnan(r)) r = 0.0f;
      r = r < -127.0f ? -127.0f : r > 127.0f ? 127.0f : r;
      a.v[i] = static_cast<std::int32_t>(std::nearbyint(r)) + 128;
    }
    return a;
  }
  // u = clamp(round_half_even(x * reciprocal), 0, 255), NaN -> 0.
  static Acc quantize_unsigned(const F& x, float reciprocal) {
    Acc a;
    for (int i = 0; i < 16; ++i) {
      float r = x.v[i] * reciprocal;
      if (std::isnan(r)) r = 0.0f;
      r = r < 0.0f ? 0.0f : r > 255.0f ? 255.0f : r;
      a.v[i] = static_cast<std::int32_t>(std::nearbyint(r));
    }
    return a;
  }
  // A hint (PREFETCHW) with no effect on results.
  static void prefetch_for_write(const void*) {}
  // Dword j: the low bytes of c0[j], c1[j], c2[j], c3[j], in that order.
  static Bytes pack_quads(const Acc& c0, const Acc& c1, const Acc& c2, const Acc& c3) {
    Bytes b;
    for (int j = 0; j < 16; ++j) {
      b.v[4 * j] = static_cast<std::uint8_t>(c0.v[j]);
      b.v[4 * j + 1] = static_cast<std::uint8_t>(c1.v[j]);
      b.v[4 * j + 2] = static_cast<std::uint8_t>(c2.v[j]);
      b.v[4 * j + 3] = static_cast<std::uint8_t>(c3.v[j]);
    }
    return b;
  }
  static Acc set1(std::int32_t v) {
    Acc a;
    for (std::int32_t& x : a.v) x = v;
    return a;
  }
  // VPCMPNEQD: bit j where dword j of a differs from that of b.
  static std::uint32_t differing_dwords(const Bytes& a, const Bytes& b) {
    std::uint32_t mask = 0;
    for (int j = 0; j < 16; ++j) {
      if (std::memcmp(a.v + 4 * j, b.v + 4 * j, 4) != 0) mask |= std::uint32_t{1} << j;
    }
    return mask;
  }
  // The dwords the 16-lane mask names.
  static void store_quads(std::uint8_t* p, const Bytes& b, std::uint32_t mask) {
    for (int j = 0; j < 16; ++j)
      if ((mask >> j) & 1u) std::memcpy(p + 4 * j, b.v + 4 * j, 4);
  }

  // The Winograd output transform (int8_winograd.hpp): FP32 adds, subtractions, the bias and the
  // ReLU; plain loads and stores of M.
  // A hint (PREFETCHT0) with no effect on results.
  static void prefetch_for_read(const void*) {}
  static F add(const F& a, const F& b) {
    F f;
    for (int i = 0; i < 16; ++i) f.v[i] = a.v[i] + b.v[i];
    return f;
  }
  static F sub(const F& a, const F& b) {
    F f;
    for (int i = 0; i < 16; ++i) f.v[i] = a.v[i] - b.v[i];
    return f;
  }
  static F bias_act(const F& a, float bias, bool relu) {
    F f;
    for (int i = 0; i < 16; ++i) {
      const float y = a.v[i] + bias;
      f.v[i] = relu ? (y > 0.0f ? y : 0.0f) : y;
    }
    return f;
  }
  static F load_f(const float* p) {
    F f;
    std::memcpy(f.v, p, sizeof(f.v));
    return f;
  }
  static void store_f(float* p, const F& f) { std::memcpy(p, f.v, sizeof(f.v)); }

  // The Winograd input transform in 16-bit integers (int8_winograd.hpp): 32 lanes of int16.
  struct I16 {
    std::int16_t v[32];
  };
  // x16 = clamp(round_half_even(x * r), -8191, 8191), NaN -> 0 (VMULPS, VMAXPS, VMINPS,
  // VCVTPS2DQ {rn-sae} zero-masked on the ordered lanes).
  static std::int16_t quantize_x16(float x, float r) {
    float v = x * r;
    if (std::isnan(v)) return 0;
    v = v < -8191.0f ? -8191.0f : v > 8191.0f ? 8191.0f : v;
    return static_cast<std::int16_t>(std::nearbyint(v));
  }
  static std::int16_t quantize_x16_f32(float x, float r) { return quantize_x16(x, r); }
  static std::int16_t quantize_x16_bf16(std::uint16_t x, float r) {
    return quantize_x16(std::bit_cast<float>(static_cast<std::uint32_t>(x) << 16), r);
  }
  // even[i] = x16 of column index + 2 i, odd[i] of index + 2 i + 1 (i < 32), for the bits of
  // the 64-lane mask, 0 elsewhere (only named lanes are read).
  static void quantize_x16_pairs_bf16(const std::uint16_t* base, std::int64_t index,
                                      std::uint64_t mask, float r, I16& even, I16& odd) {
    even = I16{}, odd = I16{};
    for (int i = 0; i < 64; ++i) {
      if ((mask >> i) & 1u) {
        const float x = std::bit_cast<float>(static_cast<std::uint32_t>(base[index + i]) << 16);
        (i % 2 == 0 ? even : odd).v[i / 2] = quantize_x16(x, r);
      }
    }
  }
  static void quantize_x16_pairs_f32(const float* base, std::int64_t index, std::uint64_t mask,
                                     float r, I16& even, I16& odd) {
    even = I16{}, odd = I16{};
    for (int i = 0; i < 64; ++i)
      if ((mask >> i) & 1u) (i % 2 == 0 ? even : odd).v[i / 2] = quantize_x16(base[index + i], r);
  }
  static I16 zero_i16() { return I16{}; }
  static I16 load_i16(const std::int16_t* p) {
    I16 a;
    std::memcpy(a.v, p, sizeof(a.v));
    return a;
  }
  static void store_i16(std::int16_t* p, const I16& a) { std::memcpy(p, a.v, sizeof(a.v)); }
  // VPADDW, VPSUBW: wrap (the transform's sums stay within int16, see int8_winograd.hpp).
  static I16 add_i16(const I16& a, const I16& b) {
    I16 c;
    for (int i = 0; i < 32; ++i) c.v[i] = static_cast<std::int16_t>(a.v[i] + b.v[i]);
    return c;
  }
  static I16 sub_i16(const I16& a, const I16& b) {
    I16 c;
    for (int i = 0; i < 32; ++i) c.v[i] = static_cast<std::int16_t>(a.v[i] - b.v[i]);
    return c;
  }
  // VPMULHRSW by m: (a m + 2^14) >> 15, arithmetic (nearest, ties up), low 16 bits.
  static I16 requantize(const I16& a, std::int16_t m) {
    I16 c;
    for (int i = 0; i < 32; ++i) {
      const std::int32_t prod = static_cast<std::int32_t>(a.v[i]) * m + (1 << 14);
      c.v[i] = static_cast<std::int16_t>(prod >> 15);
    }
    return c;
  }
  // Dword j < tiles (16 or 32) at out: u(c0[j]), u(c1[j]), u(c2[j]), u(c3[j]) with u(q) =
  // clamp(q, -127, 127) + 128 (VPACKSSWB's saturation, VPMAXSB, VPXORD 0x80; the unpacks and
  // VPERMT2Q only move bytes).
  static void store_quads_i16(std::uint8_t* out, const I16& c0, const I16& c1, const I16& c2,
                              const I16& c3, int tiles) {
    const I16* c[4] = {&c0, &c1, &c2, &c3};
    for (int j = 0; j < tiles; ++j) {
      for (int k = 0; k < 4; ++k) {
        const std::int16_t q = c[k]->v[j];
        out[4 * j + k] = static_cast<std::uint8_t>((q < -127 ? -127 : q > 127 ? 127 : q) + 128);
      }
    }
  }
};

// The tile instructions (see above), the interface of AmxInt8Tiles in int8_conv_avx512.cpp.
struct EmulatedAmxInt8Tiles {
  struct Tile {
    std::uint8_t b[16][64];
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
    std::memset(file()[T].b, 0, sizeof(Tile));
  }
  template <int T>
  static void load(const void* base, std::int64_t stride_bytes) {
    for (int r = 0; r < 16; ++r)
      std::memcpy(file()[T].b[r], static_cast<const std::uint8_t*>(base) + r * stride_bytes, 64);
  }
  template <int T>
  static void store(void* base, std::int64_t stride_bytes) {
    for (int r = 0; r < 16; ++r)
      std::memcpy(static_cast<std::uint8_t*>(base) + r * stride_bytes, file()[T].b[r], 64);
  }
  // TDPBSUD C, A, B.
  template <int C, int A, int B>
  static void dot() {
    Tile& c = file()[C];
    const Tile& a = file()[A];
    const Tile& b = file()[B];
    for (int m = 0; m < 16; ++m) {
      for (int n = 0; n < 16; ++n) {
        std::int32_t acc;
        std::memcpy(&acc, c.b[m] + 4 * n, 4);
        std::int64_t sum = acc;
        for (int k = 0; k < 16; ++k) {
          for (int i = 0; i < 4; ++i) {
            sum += static_cast<std::int64_t>(static_cast<std::int8_t>(a.b[m][4 * k + i])) *
                   b.b[k][4 * n + i];
          }
        }
        acc = EmulatedVnniIsa::wrap(sum);
        std::memcpy(c.b[m] + 4 * n, &acc, 4);
      }
    }
  }
};

}  // namespace pillarseg::cpu
