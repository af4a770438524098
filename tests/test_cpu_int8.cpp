// INT8 convolutions on the CPU (engine/cpu/int8_conv.hpp): the models of VPDPBUSD and TDPBSUD
// against hand-computed examples (operand signs, wrap-around); the quantization rules by hand;
// every kernel choice (the models everywhere, VNNI and AMX-INT8 where this CPU has them, skipped
// with the reason where not) against a reference that quantizes by the same rules and accumulates
// in int64 (bit for bit, so the INT32 accumulators match exactly) and against the same sums in
// double (within the FP32 epilogue's rounding), at shapes that leave every tail (channels not
// multiples of 4, 16 or 64, widths not multiples of 16, columns past the 8- and 32-column tiles),
// with guard words around the outputs; the transposed 2x2 convolution; results independent of
// the thread count; a packing with its K order swapped fails; and against FP32, the error on
// random data is what the quantization noise predicts. Each in both input modes: signed (u = q +
// 128, compensated) and non-negative (u = q in 0..255, padding 0, no compensation), the latter
// with inputs past 127 sx (which the signed rule would clamp) and a hand-computed case that a
// padding of 128 or a compensation taken off would fail; for a non-negative input its error is
// about half the signed mode's.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "core/parallel.hpp"
#include "engine/cpu/int8_conv.hpp"
#include "engine/cpu/int8_isa_emulated.hpp"
#include "weights_io/half.hpp"

using namespace pillarseg;
using cpu::EmulatedAmxInt8Tiles;
using cpu::EmulatedVnniIsa;
using cpu::Int8Kernels;

namespace {

// ---- the instruction models ----

TEST(EmulatedVnniIsa, DpbusdMultipliesUnsignedBySignedBytesAndWraps) {
  EmulatedVnniIsa::Bytes a{}, b{};
  // Lane 0: a = (255, 1, 128, 0) unsigned, b = (0x80, 127, 0xFF, 5) signed: (-128, 127, -1, 5).
  const std::uint8_t a0[4] = {255, 1, 128, 0}, b0[4] = {0x80, 127, 0xFF, 5};
  std::memcpy(a.v, a0, 4);
  std::memcpy(b.v, b0, 4);
  // Lane 1: every byte 255 by 127, near the top of the int32 range.
  for (int i = 4; i < 8; ++i) a.v[i] = 255, b.v[i] = 127;
  EmulatedVnniIsa::Acc acc = EmulatedVnniIsa::zero();
  acc.v[0] = 10;
  acc.v[1] = std::numeric_limits<std::int32_t>::max() - 10;
  acc.v[2] = -3;  // lane 2: no products (zero bytes)
  const EmulatedVnniIsa::Acc r = EmulatedVnniIsa::dot(acc, a, b);
  // 10 + 255 (-128) + 1 127 + 128 (-1) + 0 = 10 - 32640 + 127 - 128 = -32631.
  EXPECT_EQ(r.v[0], -32631);
  // (2^31 - 11) + 4 32385 = 2^31 + 129529 wraps to -2^31 + 129529 (no saturation).
  EXPECT_EQ(r.v[1], -2147483648 + 129529);
  EXPECT_EQ(r.v[2], -3);
}

TEST(EmulatedAmxInt8Tiles, DpbsudMultipliesSignedAByUnsignedBAndWraps) {
  using Tiles = EmulatedAmxInt8Tiles;
  alignas(64) std::uint8_t a[16][64] = {}, b[16][64] = {};
  alignas(64) std::int32_t c[16][16] = {};
  // C[0][1] += A[0] . B[:, 1]: A row 0 bytes (0xFF, 2, 0, 0 | 0x80, 0, 0, 0) are signed (-1, 2 |
  // -128); B row 0 dword 1 (200, 3, 0, 0) and row 1 dword 1 (255, 0, 0, 0) are unsigned.
  a[0][0] = 0xFF, a[0][1] = 2, a[0][4] = 0x80;
  b[0][4] = 200, b[0][5] = 3, b[1][4] = 255;
  // C[3][0]: A row 3 all -128, B's dword 0 of every row all 255: 64 (-128 255) = -2088960,
  // added to -2^31 + 5 it wraps.
  for (int k = 0; k < 64; ++k) a[3][k] = 0x80;
  for (int k = 0; k < 16; ++k) std::memset(&b[k][0], 255, 4);
  c[0][1] = 7;
  c[3][0] = std::numeric_limits<std::int32_t>::min() + 5;
  Tiles::load<0>(c, 64);
  Tiles::load<4>(a, 64);
  Tiles::load<6>(b, 64);
  Tiles::dot<0, 4, 6>();
  Tiles::store<0>(c, 64);
  // 7 + (-1) 200 + 2 3 + (-128) 255 = 7 - 200 + 6 - 32640.
  EXPECT_EQ(c[0][1], -32827);
  // -2^31 + 5 - 2088960 + 2^32.
  EXPECT_EQ(c[3][0], 2145394693);
  // Row 0 against B's dword 0 (255 in every byte of rows 0..15): -1 255 + 2 255 + (-128) 255.
  EXPECT_EQ(c[0][0], 255 * (-1 + 2 - 128));
  EXPECT_EQ(c[1][1], 0);
}

TEST(Int8Kernels, NativeChoiceFollowsTheCpuAndPillarsegCpuAmx) {
  const char* saved = std::getenv("PILLARSEG_CPU_AMX");
  const std::string saved_value = saved != nullptr ? saved : "";
  ::unsetenv("PILLARSEG_CPU_AMX");
  EXPECT_EQ(cpu::native_int8_kernels(),
            cpu::amx_int8_available() ? Int8Kernels::Amx : Int8Kernels::Vnni);
  ::setenv("PILLARSEG_CPU_AMX", "0", 1);
  EXPECT_EQ(cpu::native_int8_kernels(), Int8Kernels::Vnni);
  if (saved != nullptr) {
    ::setenv("PILLARSEG_CPU_AMX", saved_value.c_str(), 1);
  } else {
    ::unsetenv("PILLARSEG_CPU_AMX");
  }
  std::string why;
  const bool amx = cpu::amx_int8_available(&why);
  EXPECT_EQ(amx, why.empty()) << why;
  if (amx) {
    EXPECT_TRUE(cpu::avx512_vnni_available());  // AMX's epilogue and quantization are VNNI's
  }
  std::printf("this CPU: avx512_vnni %s, amx_int8 %s%s\n",
              cpu::avx512_vnni_available() ? "yes" : "no", amx ? "yes" : "no",
              amx ? "" : (" (" + why + ")").c_str());
}

// ---- the quantization rules ----

TEST(Int8Quantize, RoundsHalfToEvenAndClamps) {
  const float r = 1.0f / 0.5f;                 // sx = 0.5
  EXPECT_EQ(cpu::quantize_int8(0.25f, r), 0);  // 0.5 -> 0
  EXPECT_EQ(cpu::quantize_int8(0.75f, r), 2);  // 1.5 -> 2
  EXPECT_EQ(cpu::quantize_int8(1.25f, r), 2);  // 2.5 -> 2
  EXPECT_EQ(cpu::quantize_int8(-0.75f, r), -2);
  EXPECT_EQ(cpu::quantize_int8(-0.25f, r), 0);
  EXPECT_EQ(cpu::quantize_int8(63.25f, r), 126);  // 126.5 -> 126
  EXPECT_EQ(cpu::quantize_int8(63.75f, r), 127);  // 127.5 clamped to 127 first
  EXPECT_EQ(cpu::quantize_int8(1e9f, r), 127);
  EXPECT_EQ(cpu::quantize_int8(-1e9f, r), -127);
  EXPECT_EQ(cpu::quantize_int8(std::numeric_limits<float>::infinity(), r), 127);
  EXPECT_EQ(cpu::quantize_int8(-std::numeric_limits<float>::infinity(), r), -127);
  EXPECT_EQ(cpu::quantize_int8(std::numeric_limits<float>::quiet_NaN(), r), 0);
}

TEST(Int8Quantize, NonNegativeRoundsHalfToEvenAndClampsToAByte) {
  const float r = 1.0f / 0.5f;                     // sx = 0.5
  EXPECT_EQ(cpu::quantize_uint8(0.25f, r), 0);     // 0.5 -> 0
  EXPECT_EQ(cpu::quantize_uint8(0.75f, r), 2);     // 1.5 -> 2
  EXPECT_EQ(cpu::quantize_uint8(1.25f, r), 2);     // 2.5 -> 2
  EXPECT_EQ(cpu::quantize_uint8(63.75f, r), 128);  // 127.5 -> 128: past the signed rule's 127
  EXPECT_EQ(cpu::quantize_uint8(64.25f, r), 128);  // 128.5 -> 128
  EXPECT_EQ(cpu::quantize_uint8(100.0f, r), 200);
  EXPECT_EQ(cpu::quantize_uint8(127.25f, r), 254);  // 254.5 -> 254
  EXPECT_EQ(cpu::quantize_uint8(127.4f, r), 255);   // 254.8 -> 255
  EXPECT_EQ(cpu::quantize_uint8(127.75f, r), 255);  // 255.5 clamped to 255 first
  EXPECT_EQ(cpu::quantize_uint8(1e9f, r), 255);
  EXPECT_EQ(cpu::quantize_uint8(-0.2f, r), 0);  // -0.4 -> 0
  EXPECT_EQ(cpu::quantize_uint8(-0.3f, r), 0);  // -0.6 -> 0
  EXPECT_EQ(cpu::quantize_uint8(-0.0f, r), 0);
  EXPECT_EQ(cpu::quantize_uint8(-1e9f, r), 0);
  EXPECT_EQ(cpu::quantize_uint8(std::numeric_limits<float>::infinity(), r), 255);
  EXPECT_EQ(cpu::quantize_uint8(-std::numeric_limits<float>::infinity(), r), 0);
  EXPECT_EQ(cpu::quantize_uint8(std::numeric_limits<float>::quiet_NaN(), r), 0);
  // The same product x r as the signed rule: below 127 both give the same code.
  const float r3 = 1.0f / 0.013f;
  for (int i = 0; i <= 1000; ++i) {
    const float x = 1.651f * static_cast<float>(i) / 1000.0f;  // x r up to 127
    EXPECT_EQ(cpu::quantize_uint8(x, r3), cpu::quantize_int8(x, r3)) << x;
  }
}

TEST(Int8Quantize, WeightsPerOutputChannelWithCompensation) {
  // w (3, 1, 1, 2): channel 0 (0.5, -1.27): scale 0.01, q (50, -127); channel 1 all zero: scale
  // 0, q 0; channel 2 (0.3, 0.1): scale 0.3 / 127, q (127, 42.33 -> 42).
  std::vector<float> w = {0.5f, -1.27f, 0.0f, 0.0f, 0.3f, 0.1f}, bias = {1.0f, 2.0f, 3.0f};
  for (Int8Kernels k : {Int8Kernels::Emulated, Int8Kernels::AmxEmulated}) {
    cpu::Int8ConvWeights p;
    cpu::prepare_int8_conv(k, Ref{w.data(), {3, 1, 1, 2}}, Ref{bias.data(), {3}}, p);
    EXPECT_FLOAT_EQ(p.scale[0], 0.01f);
    EXPECT_EQ(p.scale[1], 0.0f);
    EXPECT_FLOAT_EQ(p.scale[2], 0.3f / 127.0f);
    EXPECT_EQ(p.q, (std::vector<std::int8_t>{50, -127, 0, 0, 127, 42}));
    EXPECT_EQ(p.compensation, (std::vector<std::int32_t>{128 * -77, 0, 128 * 169}));
    EXPECT_EQ(p.bias, bias);
  }
  // Transposed w (I 2, O 1, 2, 2): one output channel over both inputs and all four sub-pixels,
  // max 2.54: scale 0.02; column n = 4 o + s sums its sub-pixel s over the inputs.
  std::vector<float> wt = {2.54f, 0.2f, -0.2f, 0.0f, 0.02f, 0.0f, 0.0f, -2.54f}, bt = {0.5f};
  cpu::Int8ConvWeights t;
  cpu::prepare_int8_conv_transpose(Int8Kernels::Emulated, Ref{wt.data(), {2, 1, 2, 2}},
                                   Ref{bt.data(), {1}}, t);
  EXPECT_FLOAT_EQ(t.scale[0], 0.02f);
  EXPECT_EQ(t.q, (std::vector<std::int8_t>{127, 10, -10, 0, 1, 0, 0, -127}));
  EXPECT_EQ(t.compensation,
            (std::vector<std::int32_t>{128 * 128, 128 * 10, 128 * -10, 128 * -127}));
  EXPECT_EQ(t.bias, (std::vector<float>{0.5f, 0.5f, 0.5f, 0.5f}));
}

// ---- the convolutions against the reference ----

std::vector<Int8Kernels> kernels_to_test() {
  std::vector<Int8Kernels> list = {Int8Kernels::Emulated, Int8Kernels::AmxEmulated};
  if (cpu::avx512_vnni_available()) list.push_back(Int8Kernels::Vnni);
  if (cpu::amx_int8_available()) list.push_back(Int8Kernels::Amx);
  return list;
}

std::vector<float> random_values(std::int64_t n, std::uint32_t seed, float lo, float hi) {
  std::mt19937 gen(seed);
  std::uniform_real_distribution<float> d(lo, hi);
  std::vector<float> v(static_cast<size_t>(n));
  for (float& x : v) x = d(gen);
  return v;
}

// An activation tensor in FP32 or BF16 (its values rounded), with its values as floats.
struct Input {
  Shape shape;
  std::vector<float> values;
  std::vector<std::uint16_t> bits;
  bool half = false;
  ActRef ref() {
    return half ? ActRef{bits.data(), shape, true} : ActRef{values.data(), shape, false};
  }
};
Input make_input(const Shape& shape, std::uint32_t seed, bool half, float lo = -2.0f,
                 float hi = 2.0f) {
  Input in{shape, random_values(shape_numel(shape), seed, lo, hi), {}, half};
  if (half) {
    for (float& v : in.values) {
      in.bits.push_back(weights::float_to_bf16_bits(v));
      v = weights::bf16_bits_to_float(in.bits.back());
    }
  }
  return in;
}

// An output tensor with guard words on both sides (FP32 or BF16).
struct Output {
  static constexpr std::int64_t kGuard = 37;
  Shape shape;
  bool half = false;
  std::vector<float> f;
  std::vector<std::uint16_t> h;
  Output(Shape s, bool bf16) : shape(std::move(s)), half(bf16) {
    const auto n = static_cast<size_t>(shape_numel(shape) + 2 * kGuard);
    if (half)
      h.assign(n, 0xABCD);
    else
      f.assign(n, 1234.5f);
  }
  ActRef ref() {
    return half ? ActRef{h.data() + kGuard, shape, true} : ActRef{f.data() + kGuard, shape, false};
  }
  bool guards_intact() const {
    const std::int64_t n = shape_numel(shape);
    for (std::int64_t i = 0; i < kGuard; ++i) {
      const size_t lo = static_cast<size_t>(i), hi = static_cast<size_t>(kGuard + n + i);
      if (half ? (h[lo] != 0xABCD || h[hi] != 0xABCD) : (f[lo] != 1234.5f || f[hi] != 1234.5f))
        return false;
    }
    return true;
  }
  std::uint32_t bits(std::int64_t i) const {  // element i's bits (FP32 or BF16)
    const size_t at = static_cast<size_t>(kGuard + i);
    if (half) return h[at];
    std::uint32_t u;
    std::memcpy(&u, &f[at], 4);
    return u;
  }
  float value(std::int64_t i) const {
    const size_t at = static_cast<size_t>(kGuard + i);
    return half ? weights::bf16_bits_to_float(h[at]) : f[at];
  }
};

// The reference: acc (int64) of each output, and y by the documented epilogue.
struct Reference {
  std::vector<std::int64_t> acc;
  std::vector<float> y;
};

// The input's code by the rule of its mode.
std::int64_t quantize(float x, float reciprocal, bool non_negative) {
  return non_negative ? cpu::quantize_uint8(x, reciprocal) : cpu::quantize_int8(x, reciprocal);
}

float epilogue(std::int64_t acc, float sx, float sw, float bias, bool relu) {
  const float v = std::fma(static_cast<float>(acc), sx * sw, bias);
  return relu ? (v > 0.0f ? v : 0.0f) : v;
}

Reference reference_conv(const Input& x, float sx, bool non_negative, const cpu::Int8ConvWeights& w,
                         int pad, bool relu) {
  const std::int64_t b_count = x.shape[0], in = x.shape[1], h = x.shape[2], wd = x.shape[3];
  const std::int64_t out = w.weight[0], kh = w.weight[2], kw = w.weight[3];
  const std::int64_t ho = h + 2 * pad - kh + 1, wo = wd + 2 * pad - kw + 1;
  const float r = 1.0f / sx;
  Reference ref;
  for (std::int64_t b = 0; b < b_count; ++b)
    for (std::int64_t o = 0; o < out; ++o)
      for (std::int64_t oy = 0; oy < ho; ++oy)
        for (std::int64_t ox = 0; ox < wo; ++ox) {
          std::int64_t acc = 0;
          for (std::int64_t c = 0; c < in; ++c)
            for (std::int64_t ky = 0; ky < kh; ++ky)
              for (std::int64_t kx = 0; kx < kw; ++kx) {
                const std::int64_t iy = oy + ky - pad, ix = ox + kx - pad;
                if (iy < 0 || iy >= h || ix < 0 || ix >= wd) continue;
                const float v = x.values[static_cast<size_t>(((b * in + c) * h + iy) * wd + ix)];
                acc += quantize(v, r, non_negative) *
                       w.q[static_cast<size_t>(((o * in + c) * kh + ky) * kw + kx)];
              }
          ref.acc.push_back(acc);
          ref.y.push_back(epilogue(acc, sx, w.scale[static_cast<size_t>(o)],
                                   w.bias[static_cast<size_t>(o)], relu));
        }
  return ref;
}

Reference reference_conv_transpose(const Input& x, float sx, bool non_negative,
                                   const cpu::Int8ConvWeights& w) {
  const std::int64_t b_count = x.shape[0], in = x.shape[1], h = x.shape[2], wd = x.shape[3];
  const std::int64_t out = w.weight[1];
  const float r = 1.0f / sx;
  Reference ref;
  for (std::int64_t b = 0; b < b_count; ++b)
    for (std::int64_t o = 0; o < out; ++o)
      for (std::int64_t y = 0; y < 2 * h; ++y)
        for (std::int64_t xx = 0; xx < 2 * wd; ++xx) {
          const std::int64_t s = (y % 2) * 2 + xx % 2;
          std::int64_t acc = 0;
          for (std::int64_t c = 0; c < in; ++c) {
            const float v = x.values[static_cast<size_t>(((b * in + c) * h + y / 2) * wd + xx / 2)];
            acc += quantize(v, r, non_negative) * w.q[static_cast<size_t>((c * out + o) * 4 + s)];
          }
          ref.acc.push_back(acc);
          ref.y.push_back(epilogue(acc, sx, w.scale[static_cast<size_t>(o)],
                                   w.bias[static_cast<size_t>(4 * o)], false));
        }
  return ref;
}

// y against the reference: bit for bit (FP32, or the BF16 rounding of the reference's FP32), and
// within the FP32 epilogue's rounding of acc sx sw + bias in double. Returns the mismatches.
std::int64_t compare(const Output& y, const Reference& ref, const cpu::Int8ConvWeights& w, float sx,
                     bool relu, std::int64_t plane, std::int64_t out_channels, std::string* first) {
  const std::int64_t columns_per_channel = w.transposed ? 4 : 1;  // bias is per GEMM column
  std::int64_t bad = 0;
  for (std::int64_t i = 0; i < static_cast<std::int64_t>(ref.y.size()); ++i) {
    const float want = ref.y[static_cast<size_t>(i)];
    const std::uint32_t want_bits = y.half ? weights::float_to_bf16_bits(want) : [&] {
      std::uint32_t u;
      std::memcpy(&u, &want, 4);
      return u;
    }();
    const std::int64_t o = i / plane % out_channels;
    const double exact_pre = static_cast<double>(ref.acc[static_cast<size_t>(i)]) * sx *
                                 w.scale[static_cast<size_t>(o)] +
                             w.bias[static_cast<size_t>(columns_per_channel * o)];
    const double exact = relu ? std::max(exact_pre, 0.0) : exact_pre;
    // float(acc), sx sw and the FMA each round once (and BF16 once more).
    const double tol = (y.half ? 0x1p-8 : 0.0) * std::abs(exact) +
                       4 * 0x1p-24 *
                           (std::abs(static_cast<double>(ref.acc[static_cast<size_t>(i)]) * sx *
                                     w.scale[static_cast<size_t>(o)]) +
                            std::abs(exact)) +
                       1e-30;
    const bool ok = y.bits(i) == want_bits && std::abs(y.value(i) - exact) <= tol;
    if (!ok && bad++ == 0 && first != nullptr) {
      *first = "element " + std::to_string(i) + ": got " + std::to_string(y.value(i)) + " (bits " +
               std::to_string(y.bits(i)) + "), want " + std::to_string(want) + " (bits " +
               std::to_string(want_bits) + "), double " + std::to_string(exact);
    }
  }
  return bad;
}

struct ConvCase {
  std::int64_t batch, in, out, h, w, k;
  int pad;
};
std::string name(const ConvCase& c) {
  return std::to_string(c.batch) + "x" + std::to_string(c.in) + "->" + std::to_string(c.out) +
         " @" + std::to_string(c.h) + "x" + std::to_string(c.w) + " k" + std::to_string(c.k) +
         " pad" + std::to_string(c.pad);
}

// Channels not multiples of 4, 16 (AMX's quad block: 64 channels) or 8 / 32 columns; widths below,
// at and past 16, 32 and 48 pixels; 1x1, 3x3, 5x5; pad 0.
const ConvCase kConvCases[] = {
    {1, 5, 3, 7, 19, 3, 1}, {2, 16, 12, 5, 33, 3, 1},  {1, 67, 40, 4, 50, 3, 1},
    {1, 3, 9, 6, 8, 1, 0},  {1, 4, 5, 9, 11, 5, 2},    {1, 6, 4, 6, 7, 3, 0},
    {1, 2, 2, 1, 1, 3, 1},  {1, 130, 33, 3, 16, 3, 1}, {1, 8, 70, 2, 49, 3, 1},
};

// The input of either mode for the bit-for-bit tests, with its scale: signed, |x| up to 2 and sx
// = 1.9 / 127, so that some values clamp; non-negative, x in [0, 2.2) and sx = 2 / 255: most
// codes past 127 (where the signed rule would clamp), some clamped at 255, and a few negatives,
// NaN and infinities for the rule's edges.
Input mode_input(const Shape& shape, std::uint32_t seed, bool half, bool non_negative, float& sx) {
  if (!non_negative) {
    sx = 1.9f / 127.0f;
    return make_input(shape, seed, half);
  }
  sx = 2.0f / 255.0f;
  Input x = make_input(shape, seed, half, 0.0f, 2.2f);
  const float special[] = {-0.5f, -0.0f, std::numeric_limits<float>::quiet_NaN(),
                           std::numeric_limits<float>::infinity(),
                           -std::numeric_limits<float>::infinity()};
  for (size_t i = 0; i < 5 && 7 * i < x.values.size(); ++i) {
    x.values[7 * i] = special[i];
    if (half) x.bits[7 * i] = weights::float_to_bf16_bits(special[i]);
  }
  return x;
}
const char* mode_name(bool non_negative) {
  return non_negative ? "non-negative" : "signed";
}

// The case's convolution with random weights in [-0.3, 0.3) (seed) and biases in [-1, 1) (seed +
// 1), prepared for `kernels`.
cpu::Int8ConvWeights random_conv(Int8Kernels kernels, const ConvCase& c, std::uint32_t seed) {
  const std::vector<float> w = random_values(c.out * c.in * c.k * c.k, seed, -0.3f, 0.3f);
  const std::vector<float> bias = random_values(c.out, seed + 1, -1.0f, 1.0f);
  cpu::Int8ConvWeights p;
  cpu::prepare_int8_conv(kernels, Ref{const_cast<float*>(w.data()), {c.out, c.in, c.k, c.k}},
                         Ref{const_cast<float*>(bias.data()), {c.out}}, p);
  return p;
}

TEST(Int8Conv, EveryKernelMatchesTheReferenceBitForBit) {
  for (Int8Kernels kernels : kernels_to_test()) {
    for (const ConvCase& c : kConvCases) {
      const cpu::Int8ConvWeights p = random_conv(kernels, c, 7);
      for (const bool non_negative : {false, true}) {
        for (const bool x_half : {false, true}) {
          for (const bool y_half : {false, true}) {
            for (const bool relu : {false, true}) {
              float sx = 0.0f;
              Input x = mode_input({c.batch, c.in, c.h, c.w}, 11, x_half, non_negative, sx);
              const std::int64_t ho = c.h + 2 * c.pad - c.k + 1, wo = c.w + 2 * c.pad - c.k + 1;
              Output y({c.batch, c.out, ho, wo}, y_half);
              cpu::Int8ConvWorkspace ws;
              cpu::int8_conv2d_forward(kernels, x.ref(), sx, non_negative, p, c.pad, relu, y.ref(),
                                       ws);
              const Reference ref = reference_conv(x, sx, non_negative, p, c.pad, relu);
              std::string first;
              EXPECT_EQ(compare(y, ref, p, sx, relu, ho * wo, c.out, &first), 0)
                  << cpu::int8_kernels_name(kernels) << " " << name(c) << " "
                  << mode_name(non_negative) << " x " << (x_half ? "bf16" : "fp32") << " y "
                  << (y_half ? "bf16" : "fp32") << " relu " << relu << ": " << first;
              EXPECT_TRUE(y.guards_intact()) << cpu::int8_kernels_name(kernels) << " " << name(c);
            }
          }
        }
      }
    }
  }
}

// A non-negative input by hand: 1 -> 1 channel, 3x3 weights all 1 (sw = 1 / 127, qw = 127), pad
// 1, x = 2 everywhere on a 3x3 image with sx = 0.01: q = 200 (past the signed rule's 127), and the
// output is the count of taps inside the image times 200 127 sx sw = 2: 8 at the corners, 12 at
// the edges, 18 in the middle. A padding of 128 would add 128 127 sx sw = 1.28 for each tap
// outside (a corner 14.4), a compensation taken off 9 128 127 sx sw = 11.52; the signed rule gives
// 127 / 200 of these values.
TEST(Int8Conv, NonNegativeInputIsUnshiftedAndPaddedWithZero) {
  const std::vector<float> w(9, 1.0f), bias = {0.0f};
  const float want[9] = {8, 12, 8, 12, 18, 12, 8, 12, 8};
  for (Int8Kernels kernels : kernels_to_test()) {
    cpu::Int8ConvWeights p;
    cpu::prepare_int8_conv(kernels, Ref{const_cast<float*>(w.data()), {1, 1, 3, 3}},
                           Ref{const_cast<float*>(bias.data()), {1}}, p);
    ASSERT_EQ(p.q, std::vector<std::int8_t>(9, 127));
    Input x{{1, 1, 3, 3}, std::vector<float>(9, 2.0f), {}, false};
    for (const bool non_negative : {true, false}) {
      Output y({1, 1, 3, 3}, false);
      cpu::Int8ConvWorkspace ws;
      cpu::int8_conv2d_forward(kernels, x.ref(), 0.01f, non_negative, p, 1, false, y.ref(), ws);
      for (int i = 0; i < 9; ++i) {
        const float expected = non_negative ? want[i] : want[i] * 127.0f / 200.0f;
        EXPECT_NEAR(y.value(i), expected, 1e-5f * expected)
            << cpu::int8_kernels_name(kernels) << " " << mode_name(non_negative) << " pixel " << i;
      }
      EXPECT_TRUE(y.guards_intact());
    }
  }
}

// Images whose quantized rows are wide enough (64 or 32 channel quads by 700 to 1000 pixels: 130
// to 200 KiB a row) that a thread's band of rows (about 1 MiB) holds only a few of them: the work
// is cut into bands, the rows two bands share carried from one to the next, and thread runs end
// inside bands; 3x3 and 5x5 (reach 3 and 5) and the transposed convolution (reach 1).
TEST(Int8Conv, WideImagesInManyBandsMatchTheReference) {
  const ConvCase cases[] = {{1, 256, 9, 8, 700, 3, 1}, {1, 128, 4, 9, 1000, 5, 2}};
  for (Int8Kernels kernels : kernels_to_test()) {
    for (const ConvCase& c : cases) {
      const cpu::Int8ConvWeights p = random_conv(kernels, c, 101);
      for (const int threads : {1, 3}) {
        ScopedThreads scoped(threads);
        const bool non_negative = threads == 3;
        float sx = 0.0f;
        Input x = mode_input({c.batch, c.in, c.h, c.w}, 103, true, non_negative, sx);
        Output y({c.batch, c.out, c.h, c.w}, true);
        cpu::Int8ConvWorkspace ws;
        cpu::int8_conv2d_forward(kernels, x.ref(), sx, non_negative, p, c.pad, true, y.ref(), ws);
        std::string first;
        EXPECT_EQ(compare(y, reference_conv(x, sx, non_negative, p, c.pad, true), p, sx, true,
                          c.h * c.w, c.out, &first),
                  0)
            << cpu::int8_kernels_name(kernels) << " " << name(c) << " threads " << threads << ": "
            << first;
        EXPECT_TRUE(y.guards_intact());
      }
    }
    const std::vector<float> w = random_values(256 * 3 * 4, 104, -0.5f, 0.5f), bias(3, 0.25f);
    cpu::Int8ConvWeights p;
    cpu::prepare_int8_conv_transpose(kernels, Ref{const_cast<float*>(w.data()), {256, 3, 2, 2}},
                                     Ref{const_cast<float*>(bias.data()), {3}}, p);
    ScopedThreads scoped(3);
    float sx = 0.0f;
    Input x = mode_input({2, 256, 7, 800}, 105, false, false, sx);
    Output y({2, 3, 14, 1600}, false);
    cpu::Int8ConvWorkspace ws;
    cpu::int8_conv_transpose2d_forward(kernels, x.ref(), sx, false, p, y.ref(), ws);
    std::string first;
    EXPECT_EQ(
        compare(y, reference_conv_transpose(x, sx, false, p), p, sx, false, 14 * 1600, 3, &first),
        0)
        << cpu::int8_kernels_name(kernels) << " transposed: " << first;
    EXPECT_TRUE(y.guards_intact());
  }
}

// A scan's BEV grid is mostly empty: the U-Net's canvas is 0 there and the first layers' outputs
// one constant vector. The windows without a busy input pixel (int8_microkernel.hpp) skip their
// products and take the accumulators of a window of the image's reference pixel (int8_conv.cpp:
// one of the pixels 8 rows and columns in from the corners). Inputs of one background but for a
// few pixels (at the image's corners and edges, at and beside the 16- and 48-pixel vector and
// tile boundaries, a lone one inside), or a row of them, or none: a zero background (the
// padding's quads; values below half a step quantize to it too), and a constant one of random
// values per channel, whose padding is busy, with the pixel at row and column 8 in the background
// or busy itself. Every output must still be the reference's bit for bit, in both modes (the
// signed one's idle accumulator for a zero background is the compensation, not 0), on a direct
// 3x3, a 5x5 and a 1x1 kernel and the transposed convolution, over several bands and threads.
TEST(Int8Conv, EmptyWindowsMatchTheReferenceBitForBit) {
  const ConvCase cases[] = {{2, 6, 10, 9, 100, 3, 1},
                            {1, 67, 33, 7, 130, 5, 2},
                            {1, 8, 9, 5, 70, 1, 0},
                            {1, 160, 20, 6, 70, 3, 1}};
  const std::int64_t columns[] = {0, 1, 15, 16, 17, 31, 32, 47, 48, 49, 64, 95, 96};
  for (Int8Kernels kernels : kernels_to_test()) {
    for (const ConvCase& c : cases) {
      const cpu::Int8ConvWeights p = random_conv(kernels, c, 201);
      // Zero background: scattered pixels, a busy row, all zero; constant background: scattered
      // pixels, and the reference pixel busy too; the first half of the channels scattered pixels
      // on zero, the others dense (the concatenation of a canvas and a decoder's output: the busy
      // bits for the leading quads only, 1, 8, 20 or on AMX 16 of them).
      for (const int pattern : {0, 1, 2, 3, 4, 5}) {
        for (const bool non_negative : {false, true}) {
          ScopedThreads scoped(pattern == 1 ? 3 : 2);
          float sx = 0.0f;
          const Input dense =
              mode_input({c.batch, c.in, c.h, c.w}, 203, pattern % 2 == 0, non_negative, sx);
          Input x = dense;
          const std::int64_t plane = c.h * c.w;
          const bool constant = pattern >= 3;
          std::vector<bool> keep(static_cast<size_t>(c.batch * plane), false);
          if (pattern == 4) {
            keep[static_cast<size_t>(std::min<std::int64_t>(8, c.h - 1) * c.w + 8)] = true;
          }
          if (pattern == 0 || pattern == 5 || constant) {
            for (const std::int64_t col : columns) {
              if (col >= c.w) continue;
              keep[static_cast<size_t>(col)] = true;  // first row
              keep[static_cast<size_t>((c.batch - 1) * plane + (c.h - 1) * c.w + col)] =
                  true;  // last
            }
            keep[static_cast<size_t>(plane / 2 + 3)] = true;      // a lone pixel inside
            keep[static_cast<size_t>(c.w * 2 + c.w - 1)] = true;  // the right edge
          } else if (pattern == 1) {
            for (std::int64_t col = 0; col < c.w; ++col)
              keep[static_cast<size_t>(3 * c.w + col)] = true;
          }
          for (std::int64_t b = 0; b < c.batch; ++b) {
            for (std::int64_t ch = 0; ch < c.in; ++ch) {
              if (pattern == 5 && c.in >= 8 && ch >= c.in / 2) continue;
              for (std::int64_t i = 0; i < plane; ++i) {
                if (keep[static_cast<size_t>(b * plane + i)]) continue;
                const size_t at = static_cast<size_t>((b * c.in + ch) * plane + i);
                // Zero, or for one pixel in 5 a value below half a quantization step; or channel
                // ch's value at pixel 5 of image 0.
                if (constant) {
                  x.values[at] = dense.values[static_cast<size_t>(ch * plane + 5)];
                } else {
                  x.values[at] = i % 5 == 0 ? 0.4f * sx : 0.0f;
                }
                if (x.half) x.bits[at] = weights::float_to_bf16_bits(x.values[at]);
                if (x.half) x.values[at] = weights::bf16_bits_to_float(x.bits[at]);
              }
            }
          }
          const std::int64_t ho = c.h + 2 * c.pad - c.k + 1, wo = c.w + 2 * c.pad - c.k + 1;
          Output y({c.batch, c.out, ho, wo}, pattern == 1);
          cpu::Int8ConvWorkspace ws;
          cpu::int8_conv2d_forward(kernels, x.ref(), sx, non_negative, p, c.pad, true, y.ref(), ws);
          std::string first;
          EXPECT_EQ(compare(y, reference_conv(x, sx, non_negative, p, c.pad, true), p, sx, true,
                            ho * wo, c.out, &first),
                    0)
              << cpu::int8_kernels_name(kernels) << " " << c.k << "x" << c.k << " pattern "
              << pattern << " " << mode_name(non_negative) << ": " << first;
          EXPECT_TRUE(y.guards_intact());
          if (c.k != 3) continue;
          // The transposed convolution on the same input.
          const std::vector<float> wt = random_values(c.in * 6 * 4, 204, -0.5f, 0.5f);
          const std::vector<float> bt = random_values(6, 205, -1.0f, 1.0f);
          cpu::Int8ConvWeights pt;
          cpu::prepare_int8_conv_transpose(kernels,
                                           Ref{const_cast<float*>(wt.data()), {c.in, 6, 2, 2}},
                                           Ref{const_cast<float*>(bt.data()), {6}}, pt);
          Output yt({c.batch, 6, 2 * c.h, 2 * c.w}, false);
          cpu::int8_conv_transpose2d_forward(kernels, x.ref(), sx, non_negative, pt, yt.ref(), ws);
          EXPECT_EQ(compare(yt, reference_conv_transpose(x, sx, non_negative, pt), pt, sx, false,
                            4 * plane, 6, &first),
                    0)
              << cpu::int8_kernels_name(kernels) << " transposed pattern " << pattern << " "
              << mode_name(non_negative) << ": " << first;
          EXPECT_TRUE(yt.guards_intact());
        }
      }
    }
  }
}

TEST(Int8Conv, TransposedMatchesTheReferenceBitForBit) {
  struct Case {
    std::int64_t batch, in, out, h, w;
  };
  const Case cases[] = {
      {1, 5, 3, 4, 7}, {2, 70, 9, 3, 20}, {1, 16, 16, 2, 17}, {1, 1, 1, 1, 1}, {1, 9, 12, 2, 40}};
  for (Int8Kernels kernels : kernels_to_test()) {
    for (const Case& c : cases) {
      const std::vector<float> w = random_values(c.in * c.out * 4, 17, -0.5f, 0.5f);
      const std::vector<float> bias = random_values(c.out, 18, -1.0f, 1.0f);
      cpu::Int8ConvWeights p;
      cpu::prepare_int8_conv_transpose(kernels,
                                       Ref{const_cast<float*>(w.data()), {c.in, c.out, 2, 2}},
                                       Ref{const_cast<float*>(bias.data()), {c.out}}, p);
      for (const bool non_negative : {false, true}) {
        for (const bool half : {false, true}) {
          float sx = 0.0f;
          Input x = mode_input({c.batch, c.in, c.h, c.w}, 19, half, non_negative, sx);
          Output y({c.batch, c.out, 2 * c.h, 2 * c.w}, half);
          cpu::Int8ConvWorkspace ws;
          cpu::int8_conv_transpose2d_forward(kernels, x.ref(), sx, non_negative, p, y.ref(), ws);
          const Reference ref = reference_conv_transpose(x, sx, non_negative, p);
          std::string first;
          EXPECT_EQ(compare(y, ref, p, sx, false, 4 * c.h * c.w, c.out, &first), 0)
              << cpu::int8_kernels_name(kernels) << " " << c.in << "->" << c.out << " @" << c.h
              << "x" << c.w << " " << mode_name(non_negative) << (half ? " bf16" : " fp32") << ": "
              << first;
          EXPECT_TRUE(y.guards_intact());
        }
      }
    }
  }
}

TEST(Int8Conv, NativeKernelsGiveTheirModelsBits) {
  std::vector<std::pair<Int8Kernels, Int8Kernels>> pairs;
  std::string why;
  if (cpu::avx512_vnni_available(&why))
    pairs.push_back({Int8Kernels::Vnni, Int8Kernels::Emulated});
  else
    std::printf("VNNI not run: %s\n", why.c_str());
  if (cpu::amx_int8_available(&why))
    pairs.push_back({Int8Kernels::Amx, Int8Kernels::AmxEmulated});
  else
    std::printf("AMX-INT8 not run: %s\n", why.c_str());
  if (pairs.empty()) GTEST_SKIP() << "this CPU runs neither VNNI nor AMX-INT8: " << why;
  // Inputs with NaN, infinities, negatives and values past the clamp, a wider layer, both modes.
  const ConvCase c{2, 96, 48, 6, 70, 3, 1};
  const std::vector<float> w = random_values(c.out * c.in * 9, 23, -0.2f, 0.2f);
  const std::vector<float> bias = random_values(c.out, 24, -1.0f, 1.0f);
  Input x = make_input({c.batch, c.in, c.h, c.w}, 25, false);
  x.values[3] = std::numeric_limits<float>::quiet_NaN();
  x.values[100] = std::numeric_limits<float>::infinity();
  x.values[2000] = -std::numeric_limits<float>::infinity();
  x.values[5000] = 1e30f;
  for (const auto& [native, model] : pairs) {
    for (const bool non_negative : {false, true}) {
      std::vector<std::uint32_t> got[2];
      for (int i = 0; i < 2; ++i) {
        const Int8Kernels k = i == 0 ? native : model;
        cpu::Int8ConvWeights p;
        cpu::prepare_int8_conv(k, Ref{const_cast<float*>(w.data()), {c.out, c.in, 3, 3}},
                               Ref{const_cast<float*>(bias.data()), {c.out}}, p);
        Output y({c.batch, c.out, c.h, c.w}, false);
        cpu::Int8ConvWorkspace ws;
        cpu::int8_conv2d_forward(k, x.ref(), non_negative ? 1.5f / 255.0f : 1.5f / 127.0f,
                                 non_negative, p, 1, true, y.ref(), ws);
        for (std::int64_t e = 0; e < shape_numel(y.shape); ++e) got[i].push_back(y.bits(e));
      }
      EXPECT_EQ(got[0], got[1]) << cpu::int8_kernels_name(native) << " " << mode_name(non_negative);
    }
  }
}

TEST(Int8Conv, ResultsDoNotDependOnTheThreadCount) {
  const ConvCase c{2, 20, 24, 9, 21, 3, 1};
  const std::vector<float> w = random_values(c.out * c.in * 9, 31, -0.3f, 0.3f);
  const std::vector<float> bias = random_values(c.out, 32, -1.0f, 1.0f);
  Input x = make_input({c.batch, c.in, c.h, c.w}, 33, true);
  for (Int8Kernels kernels : kernels_to_test()) {
    cpu::Int8ConvWeights p;
    cpu::prepare_int8_conv(kernels, Ref{const_cast<float*>(w.data()), {c.out, c.in, 3, 3}},
                           Ref{const_cast<float*>(bias.data()), {c.out}}, p);
    for (const bool non_negative : {false, true}) {
      std::vector<std::uint16_t> first;
      for (int threads : {1, 2, 3}) {
        ScopedThreads scoped(threads);
        Output y({c.batch, c.out, c.h, c.w}, true);
        cpu::Int8ConvWorkspace ws;
        cpu::int8_conv2d_forward(kernels, x.ref(), 0.02f, non_negative, p, 1, false, y.ref(), ws);
        if (first.empty()) first = y.h;
        EXPECT_EQ(y.h, first) << cpu::int8_kernels_name(kernels) << " " << mode_name(non_negative)
                              << " threads " << threads;
      }
    }
  }
}

// The reference comparison catches a packing whose K order is wrong: the four channels within a
// quad reversed, or two taps swapped.
TEST(Int8Conv, ASwappedKOrderFails) {
  const ConvCase c{1, 8, 8, 5, 20, 3, 1};
  const std::vector<float> w = random_values(c.out * c.in * 9, 41, -0.3f, 0.3f);
  const std::vector<float> bias = random_values(c.out, 42, -1.0f, 1.0f);
  Input x = make_input({c.batch, c.in, c.h, c.w}, 43, false);
  for (Int8Kernels kernels : {Int8Kernels::Emulated, Int8Kernels::AmxEmulated}) {
    cpu::Int8ConvWeights good;
    cpu::prepare_int8_conv(kernels, Ref{const_cast<float*>(w.data()), {c.out, c.in, 3, 3}},
                           Ref{const_cast<float*>(bias.data()), {c.out}}, good);
    const Reference ref = reference_conv(x, 0.015f, false, good, 1, false);
    const auto mismatches = [&](const cpu::Int8ConvWeights& p) {
      Output y({c.batch, c.out, c.h, c.w}, false);
      cpu::Int8ConvWorkspace ws;
      cpu::int8_conv2d_forward(kernels, x.ref(), 0.015f, false, p, 1, false, y.ref(), ws);
      return compare(y, ref, good, 0.015f, false, c.h * c.w, c.out, nullptr);
    };
    ASSERT_EQ(mismatches(good), 0) << cpu::int8_kernels_name(kernels);
    cpu::Int8ConvWeights reversed = good;
    for (size_t i = 0; i + 4 <= reversed.packed.size(); i += 4)
      std::reverse(reversed.packed.begin() + static_cast<std::ptrdiff_t>(i),
                   reversed.packed.begin() + static_cast<std::ptrdiff_t>(i + 4));
    EXPECT_GT(mismatches(reversed), c.h * c.w) << cpu::int8_kernels_name(kernels);
    // Taps 0 and 1 swapped: in both packings a tap's bytes are one contiguous run of `quads` x 4
    // (x 8 columns for Vnni) within a column (group).
    cpu::Int8ConvWeights swapped = good;
    const bool amx = cpu::int8_amx_family(kernels);
    const std::int64_t quads = amx ? 16 : 2, run = amx ? quads * 4 : quads * 4 * 8;
    const std::int64_t column_bytes = 9 * run;
    for (std::int64_t base = 0;
         base + column_bytes <= static_cast<std::int64_t>(swapped.packed.size());
         base += column_bytes) {
      std::swap_ranges(swapped.packed.begin() + base, swapped.packed.begin() + base + run,
                       swapped.packed.begin() + base + run);
    }
    EXPECT_GT(mismatches(swapped), c.h * c.w) << cpu::int8_kernels_name(kernels);
  }
}

TEST(Int8Conv, RejectsWhatItCannotRun) {
  const std::vector<float> w = random_values(4 * 4 * 9, 51, -0.3f, 0.3f), bias(4, 0.0f);
  cpu::Int8ConvWeights p;
  cpu::prepare_int8_conv(Int8Kernels::Emulated, Ref{const_cast<float*>(w.data()), {4, 4, 3, 3}},
                         Ref{const_cast<float*>(bias.data()), {4}}, p);
  Input x = make_input({1, 4, 5, 5}, 52, false);
  Output y({1, 4, 5, 5}, false);
  cpu::Int8ConvWorkspace ws;
  EXPECT_THROW(cpu::int8_conv2d_forward(Int8Kernels::Emulated, x.ref(), 0.0f, false, p, 1, false,
                                        y.ref(), ws),
               Error);
  EXPECT_THROW(cpu::int8_conv2d_forward(Int8Kernels::AmxEmulated, x.ref(), 0.01f, false, p, 1,
                                        false, y.ref(), ws),
               Error);  // packed for VNNI
  Output wrong({1, 4, 4, 5}, false);
  EXPECT_THROW(cpu::int8_conv2d_forward(Int8Kernels::Emulated, x.ref(), 0.01f, false, p, 1, false,
                                        wrong.ref(), ws),
               Error);
  std::vector<float> bad = w;
  bad[5] = std::numeric_limits<float>::quiet_NaN();
  EXPECT_THROW(cpu::prepare_int8_conv(Int8Kernels::Emulated, Ref{bad.data(), {4, 4, 3, 3}},
                                      Ref{const_cast<float*>(bias.data()), {4}}, p),
               Error);
}

// ---- Winograd-domain INT8 F(2x2, 3x3) ----

// V (C, tiles, 16) of one image by the kernel's FP32 operations, in the kernel's order.
std::vector<float> winograd_v(const Input& x, std::int64_t b) {
  const std::int64_t in = x.shape[1], h = x.shape[2], w = x.shape[3];
  const std::int64_t th = (h + 1) / 2, tw = (w + 1) / 2;
  std::vector<float> v(static_cast<size_t>(in * th * tw * 16));
  for (std::int64_t c = 0; c < in; ++c)
    for (std::int64_t t = 0; t < th * tw; ++t) {
      float hr[4][4];
      for (int r = 0; r < 4; ++r) {
        float d[4];
        for (int j = 0; j < 4; ++j) {
          const std::int64_t iy = 2 * (t / tw) - 1 + r, ix = 2 * (t % tw) - 1 + j;
          d[j] = iy < 0 || iy >= h || ix < 0 || ix >= w
                     ? 0.0f
                     : x.values[static_cast<size_t>(((b * in + c) * h + iy) * w + ix)];
        }
        hr[r][0] = d[0] - d[2], hr[r][1] = d[1] + d[2], hr[r][2] = d[2] - d[1];
        hr[r][3] = d[1] - d[3];
      }
      for (int j = 0; j < 4; ++j) {
        const float col[4] = {hr[0][j] - hr[2][j], hr[1][j] + hr[2][j], hr[2][j] - hr[1][j],
                              hr[1][j] - hr[3][j]};
        for (int i = 0; i < 4; ++i)
          v[static_cast<size_t>((c * th * tw + t) * 16 + 4 * i + j)] = col[i];
      }
    }
  return v;
}

// V16 (C, tiles, 16) of one image by the contract of int8_winograd.hpp: each input element to
// x16 = clamp(round_half_even(x r16), -8191, 8191) (NaN -> 0), then B^T x16 B in integers.
std::vector<std::int32_t> winograd_v16(const Input& x, std::int64_t b, float r16) {
  const std::int64_t in = x.shape[1], h = x.shape[2], w = x.shape[3];
  const std::int64_t th = (h + 1) / 2, tw = (w + 1) / 2;
  const auto x16 = [&](std::int64_t c, std::int64_t iy, std::int64_t ix) -> std::int32_t {
    if (iy < 0 || iy >= h || ix < 0 || ix >= w) return 0;
    const float v = x.values[static_cast<size_t>(((b * in + c) * h + iy) * w + ix)] * r16;
    if (std::isnan(v)) return 0;
    return static_cast<std::int32_t>(std::nearbyint(std::clamp(v, -8191.0f, 8191.0f)));
  };
  std::vector<std::int32_t> v(static_cast<size_t>(in * th * tw * 16));
  for (std::int64_t c = 0; c < in; ++c)
    for (std::int64_t t = 0; t < th * tw; ++t) {
      std::int32_t hr[4][4];
      for (int r = 0; r < 4; ++r) {
        std::int32_t d[4];
        for (int j = 0; j < 4; ++j) d[j] = x16(c, 2 * (t / tw) - 1 + r, 2 * (t % tw) - 1 + j);
        hr[r][0] = d[0] - d[2], hr[r][1] = d[1] + d[2], hr[r][2] = d[2] - d[1];
        hr[r][3] = d[1] - d[3];
      }
      for (int j = 0; j < 4; ++j) {
        const std::int32_t col[4] = {hr[0][j] - hr[2][j], hr[1][j] + hr[2][j], hr[2][j] - hr[1][j],
                                     hr[1][j] - hr[3][j]};
        for (int i = 0; i < 4; ++i)
          v[static_cast<size_t>((c * th * tw + t) * 16 + 4 * i + j)] = col[i];
      }
    }
  return v;
}

// y by the contract of int8_winograd.hpp: V16 requantized per position by its multiplier
// ((V16 m + 2^14) >> 15, clamped to +-127), int64 products, M = float(acc) (sv_eff su), the output
// transform in the kernel's order, the bias, the ReLU.
std::vector<float> reference_winograd(const Input& x, const float* sv,
                                      const cpu::Int8WinogradWeights& w, bool relu) {
  const std::int64_t batch = x.shape[0], in = x.shape[1], h = x.shape[2], wd = x.shape[3];
  const std::int64_t out = w.weight[0], th = (h + 1) / 2, tw = (wd + 1) / 2;
  const cpu::Int8WinogradInputScales scales = cpu::int8_winograd_input_scales(sv);
  std::vector<float> y(static_cast<size_t>(batch * out * h * wd));
  for (std::int64_t b = 0; b < batch; ++b) {
    const std::vector<std::int32_t> v = winograd_v16(x, b, scales.r16);
    for (std::int64_t o = 0; o < out; ++o)
      for (std::int64_t t = 0; t < th * tw; ++t) {
        float m[16];
        for (int p = 0; p < 16; ++p) {
          std::int64_t acc = 0;
          for (std::int64_t c = 0; c < in; ++c) {
            const std::int32_t v16 = v[static_cast<size_t>((c * th * tw + t) * 16 + p)];
            const std::int32_t q =
                std::clamp((v16 * scales.multiplier[p] + (1 << 14)) >> 15, -127, 127);
            acc += q * w.q[static_cast<size_t>((p * out + o) * in + c)];
          }
          m[p] = static_cast<float>(acc) *
                 (scales.sv_eff[p] * w.scale[static_cast<size_t>(p * out + o)]);
        }
        float rows[2][4];
        for (int j = 0; j < 4; ++j) {
          rows[0][j] = m[j] + m[4 + j] + m[8 + j];
          rows[1][j] = m[4 + j] - m[8 + j] - m[12 + j];
        }
        for (int dy = 0; dy < 2; ++dy) {
          const float ys[2] = {rows[dy][0] + rows[dy][1] + rows[dy][2],
                               rows[dy][1] - rows[dy][2] - rows[dy][3]};
          for (int dx = 0; dx < 2; ++dx) {
            const std::int64_t oy = 2 * (t / tw) + dy, ox = 2 * (t % tw) + dx;
            if (oy >= h || ox >= wd) continue;
            const float r = ys[dx] + w.bias[static_cast<size_t>(o)];
            y[static_cast<size_t>(((b * out + o) * h + oy) * wd + ox)] =
                relu ? (r > 0.0f ? r : 0.0f) : r;
          }
        }
      }
  }
  return y;
}

// The 16-bit transform's constants, by hand: equal scales give s16 = sv / 64 and m = 2^15 / 64 =
// 512; a position 3x finer, m = round(512 3) = 1536; one 100x finer caps s16 at its scale (m =
// 32767 for it, its effective scale 2^15 / 32767 of its own).
TEST(Int8Winograd, InputScalesByHand) {
  float sv[16];
  std::fill(sv, sv + 16, 0.5f);
  cpu::Int8WinogradInputScales s = cpu::int8_winograd_input_scales(sv);
  EXPECT_EQ(s.r16, 128.0f);
  for (int p = 0; p < 16; ++p) {
    EXPECT_EQ(s.multiplier[p], 512);
    EXPECT_EQ(s.sv_eff[p], 0.5f);
  }
  sv[5] = 0.5f / 3.0f;
  s = cpu::int8_winograd_input_scales(sv);
  EXPECT_EQ(s.r16, 128.0f);
  EXPECT_EQ(s.multiplier[5], 1536);
  EXPECT_FLOAT_EQ(s.sv_eff[5], static_cast<float>(32768.0 / 128.0 / 1536.0));
  EXPECT_EQ(s.multiplier[0], 512);
  sv[5] = 0.005f;  // 100x finer than the others: s16 = 0.005, not 0.5 / 64
  s = cpu::int8_winograd_input_scales(sv);
  EXPECT_FLOAT_EQ(s.r16, 200.0f);
  EXPECT_EQ(s.multiplier[5], 32767);
  EXPECT_FLOAT_EQ(s.sv_eff[5], static_cast<float>(0.005 * 32768.0 / 32767.0));
  EXPECT_EQ(s.multiplier[0], 328);  // round(32768 0.005 / 0.5) = round(327.68)
}

TEST(Int8Winograd, MatchesTheReferenceBitForBit) {
  struct Case {
    std::int64_t batch, in, out, h, w;
  };
  // Odd sizes, channels not multiples of 4, columns past 8, widths past 16 / 32 / 48 tiles, and
  // (1024 channels, 40 tiles a row) two blocks a tile row.
  const Case cases[] = {{1, 5, 3, 7, 19}, {2, 16, 12, 6, 33}, {1, 67, 20, 5, 40}, {1, 8, 9, 1, 1},
                        {1, 4, 8, 9, 70}, {1, 3, 17, 2, 2},   {1, 1024, 8, 2, 80}};
  std::vector<Int8Kernels> kernels = {Int8Kernels::Emulated};
  if (cpu::avx512_vnni_available()) kernels.push_back(Int8Kernels::Vnni);
  for (const Case& c : cases) {
    const std::vector<float> w = random_values(c.out * c.in * 9, 81, -0.3f, 0.3f);
    const std::vector<float> bias = random_values(c.out, 82, -1.0f, 1.0f);
    cpu::Int8WinogradWeights p;
    cpu::prepare_int8_winograd(Ref{const_cast<float*>(w.data()), {c.out, c.in, 3, 3}},
                               Ref{const_cast<float*>(bias.data()), {c.out}}, p);
    for (const bool half : {false, true}) {
      Input x = make_input({c.batch, c.in, c.h, c.w}, 83, half);
      // Scales from the maxima, a little under them so that some values clamp.
      float absmax[16], sv[16];
      cpu::int8_winograd_input_absmax(x.ref(), absmax);
      float want_max[16] = {};
      for (std::int64_t b = 0; b < c.batch; ++b) {
        const std::vector<float> v = winograd_v(x, b);
        for (size_t i = 0; i < v.size(); ++i)
          want_max[i % 16] = std::max(want_max[i % 16], std::abs(v[i]));
      }
      for (int q = 0; q < 16; ++q) {
        ASSERT_EQ(absmax[q], want_max[q]) << "position " << q;
        sv[q] = std::max(absmax[q], 1e-3f) * 0.9f / 127.0f;
      }
      for (const bool relu : {false, true}) {
        const std::vector<float> want = reference_winograd(x, sv, p, relu);
        for (Int8Kernels k : kernels) {
          Output y({c.batch, c.out, c.h, c.w}, half);
          cpu::Int8WinogradWorkspace ws;
          cpu::int8_winograd_forward(k, x.ref(), sv, p, relu, y.ref(), ws);
          std::int64_t bad = 0;
          std::string first;
          for (std::int64_t i = 0; i < static_cast<std::int64_t>(want.size()); ++i) {
            const float wv = want[static_cast<size_t>(i)];
            std::uint32_t want_bits = weights::float_to_bf16_bits(wv);
            if (!half) std::memcpy(&want_bits, &wv, 4);
            if (y.bits(i) != want_bits && bad++ == 0) {
              first = "element " + std::to_string(i) + ": got " + std::to_string(y.value(i)) +
                      ", want " + std::to_string(wv);
            }
          }
          EXPECT_EQ(bad, 0) << cpu::int8_kernels_name(k) << " " << c.in << "->" << c.out << " @"
                            << c.h << "x" << c.w << (half ? " bf16" : " fp32") << " relu " << relu
                            << ": " << first;
          EXPECT_TRUE(y.guards_intact());
        }
      }
    }
  }
  std::vector<float> w(4 * 4 * 9, 0.1f), bias(4, 0.0f);
  cpu::Int8WinogradWeights p;
  cpu::prepare_int8_winograd(Ref{w.data(), {4, 4, 3, 3}}, Ref{bias.data(), {4}}, p);
  Input x = make_input({1, 4, 4, 4}, 84, false);
  Output y({1, 4, 4, 4}, false);
  cpu::Int8WinogradWorkspace ws;
  const float sv[16] = {1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0};
  EXPECT_THROW(
      cpu::int8_winograd_forward(Int8Kernels::Emulated, x.ref(), sv, p, false, y.ref(), ws), Error);
  EXPECT_THROW(
      cpu::int8_winograd_forward(Int8Kernels::AmxEmulated, x.ref(), sv, p, false, y.ref(), ws),
      Error);
}

// Against FP32, next to the direct INT8 convolution on the same data: Winograd's quantization of
// V and U (whose entries sum up to 4 and 9 products' worth of range) costs about half again the
// direct error (bench_int8_conv --winograd simulates the same); bounded loosely here, printed.
TEST(Int8Winograd, ErrorAgainstFp32) {
  const std::int64_t in = 32, out = 16, h = 24, w = 24;
  std::mt19937 gen(91);
  std::normal_distribution<float> normal(0.0f, 1.0f);
  std::vector<float> wt(static_cast<size_t>(out * in * 9)), bias(static_cast<size_t>(out));
  for (float& v : wt) v = 0.1f * normal(gen);
  for (float& v : bias) v = 0.1f * normal(gen);
  Input x{{1, in, h, w}, std::vector<float>(static_cast<size_t>(in * h * w)), {}, false};
  for (float& v : x.values) v = std::max(normal(gen), 0.0f);  // post-ReLU activations
  cpu::Int8WinogradWeights p;
  cpu::prepare_int8_winograd(Ref{wt.data(), {out, in, 3, 3}}, Ref{bias.data(), {out}}, p);
  float sv[16];
  cpu::int8_winograd_input_absmax(x.ref(), sv);
  for (float& s : sv) s /= 127.0f;
  Output yw({1, out, h, w}, false);
  cpu::Int8WinogradWorkspace ws;
  cpu::int8_winograd_forward(Int8Kernels::Emulated, x.ref(), sv, p, false, yw.ref(), ws);
  float max_abs = 0.0f;
  for (float v : x.values) max_abs = std::max(max_abs, v);
  cpu::Int8ConvWeights pd;
  cpu::prepare_int8_conv(Int8Kernels::Emulated, Ref{wt.data(), {out, in, 3, 3}},
                         Ref{bias.data(), {out}}, pd);
  Output yd({1, out, h, w}, false);
  cpu::Int8ConvWorkspace wsd;
  cpu::int8_conv2d_forward(Int8Kernels::Emulated, x.ref(), max_abs / 127.0f, false, pd, 1, false,
                           yd.ref(), wsd);
  double signal = 0.0, e_wino = 0.0, e_direct = 0.0;
  for (std::int64_t o = 0; o < out; ++o)
    for (std::int64_t oy = 0; oy < h; ++oy)
      for (std::int64_t ox = 0; ox < w; ++ox) {
        double exact = bias[static_cast<size_t>(o)];
        for (std::int64_t c = 0; c < in; ++c)
          for (int ky = 0; ky < 3; ++ky)
            for (int kx = 0; kx < 3; ++kx) {
              const std::int64_t iy = oy + ky - 1, ix = ox + kx - 1;
              if (iy < 0 || iy >= h || ix < 0 || ix >= w) continue;
              exact += static_cast<double>(x.values[static_cast<size_t>((c * h + iy) * w + ix)]) *
                       wt[static_cast<size_t>(((o * in + c) * 3 + ky) * 3 + kx)];
            }
        const std::int64_t i = (o * h + oy) * w + ox;
        signal += exact * exact;
        e_wino += (yw.value(i) - exact) * (yw.value(i) - exact);
        e_direct += (yd.value(i) - exact) * (yd.value(i) - exact);
      }
  const double wino = std::sqrt(e_wino / signal), direct = std::sqrt(e_direct / signal);
  std::printf(
      "against FP32 (ReLU'd N(0, 1) input): relative RMS error, direct INT8 %.3f%%, "
      "Winograd-domain INT8 %.3f%%\n",
      100 * direct, 100 * wino);
  EXPECT_LT(direct, 0.03);
  EXPECT_LT(wino, 3 * direct);
  EXPECT_GT(wino, 0.5 * direct);
}

// Against FP32 on random data: each product's error is w dq + x dw with the rounding errors dq,
// dw uniform on half a step (variance sx^2 / 12, sw^2 / 12), so the output's error variance is
// sum (w^2 sx^2 + x^2 sw^2) / 12 over its products. The measured sum of squared errors over all
// outputs must be that prediction within 20% (a few thousand outputs: the ratio's spread is a
// few percent), and its relative RMS is printed.
TEST(Int8Conv, ErrorAgainstFp32IsTheQuantizationNoise) {
  const ConvCase c{1, 32, 16, 24, 24, 3, 1};
  std::mt19937 gen(61);
  std::normal_distribution<float> normal(0.0f, 1.0f);
  std::vector<float> w(static_cast<size_t>(c.out * c.in * 9)), bias(static_cast<size_t>(c.out));
  for (float& v : w) v = 0.1f * normal(gen);
  for (float& v : bias) v = 0.1f * normal(gen);
  Input x{{c.batch, c.in, c.h, c.w},
          std::vector<float>(static_cast<size_t>(c.in * c.h * c.w)),
          {},
          false};
  for (float& v : x.values) v = normal(gen);
  float max_abs = 0.0f;
  for (float v : x.values) max_abs = std::max(max_abs, std::abs(v));
  const float sx = max_abs / 127.0f;  // no clamping
  cpu::Int8ConvWeights p;
  cpu::prepare_int8_conv(Int8Kernels::Emulated, Ref{w.data(), {c.out, c.in, 3, 3}},
                         Ref{bias.data(), {c.out}}, p);
  Output y({c.batch, c.out, c.h, c.w}, false);
  cpu::Int8ConvWorkspace ws;
  cpu::int8_conv2d_forward(Int8Kernels::Emulated, x.ref(), sx, false, p, 1, false, y.ref(), ws);
  double error2 = 0.0, predicted2 = 0.0, signal2 = 0.0;
  for (std::int64_t o = 0; o < c.out; ++o) {
    const double sw = p.scale[static_cast<size_t>(o)];
    for (std::int64_t oy = 0; oy < c.h; ++oy)
      for (std::int64_t ox = 0; ox < c.w; ++ox) {
        double exact = bias[static_cast<size_t>(o)], var = 0.0;
        for (std::int64_t ci = 0; ci < c.in; ++ci)
          for (int ky = 0; ky < 3; ++ky)
            for (int kx = 0; kx < 3; ++kx) {
              const std::int64_t iy = oy + ky - 1, ix = ox + kx - 1;
              if (iy < 0 || iy >= c.h || ix < 0 || ix >= c.w) continue;
              const double xv = x.values[static_cast<size_t>((ci * c.h + iy) * c.w + ix)];
              const double wv = w[static_cast<size_t>(((o * c.in + ci) * 3 + ky) * 3 + kx)];
              exact += xv * wv;
              var += (wv * wv * sx * sx + xv * xv * sw * sw) / 12.0;
            }
        const double got = y.value((o * c.h + oy) * c.w + ox);
        error2 += (got - exact) * (got - exact);
        predicted2 += var;
        signal2 += exact * exact;
      }
  }
  std::printf(
      "INT8 against FP32: relative RMS error %.4f%%, predicted %.4f%%, measured / predicted "
      "error power %.3f\n",
      100.0 * std::sqrt(error2 / signal2), 100.0 * std::sqrt(predicted2 / signal2),
      error2 / predicted2);
  EXPECT_GT(error2 / predicted2, 0.8);
  EXPECT_LT(error2 / predicted2, 1.2);
}

// A non-negative input (ReLU'd N(0, 1)) at the same clip value, max x: the non-negative mode's
// step is clip / 255 against the signed mode's clip / 127, so its error against FP32 is about half
// (127 / 255). The weights are whole multiples of their step (qw sw = w), so that only the input's
// rounding differs between the modes.
TEST(Int8Conv, NonNegativeModeHalvesTheErrorOfANonNegativeInput) {
  const std::int64_t in = 32, out = 16, h = 24, w = 24;
  std::mt19937 gen(71);
  std::normal_distribution<float> normal(0.0f, 1.0f);
  std::uniform_int_distribution<int> step(-127, 127);
  std::vector<float> wt(static_cast<size_t>(out * in * 9)), bias(static_cast<size_t>(out));
  for (size_t i = 0; i < wt.size(); ++i)
    wt[i] = 0.01f * static_cast<float>(i % (in * 9) == 0 ? 127 : step(gen));  // sw = 0.01
  for (float& v : bias) v = 0.1f * normal(gen);
  Input x{{1, in, h, w}, std::vector<float>(static_cast<size_t>(in * h * w)), {}, false};
  for (float& v : x.values) v = std::max(normal(gen), 0.0f);
  const float clip = *std::max_element(x.values.begin(), x.values.end());
  cpu::Int8ConvWeights p;
  cpu::prepare_int8_conv(Int8Kernels::Emulated, Ref{wt.data(), {out, in, 3, 3}},
                         Ref{bias.data(), {out}}, p);
  for (size_t i = 0; i < wt.size(); ++i) {
    ASSERT_NEAR(p.q[i] * p.scale[i / static_cast<size_t>(in * 9)], wt[i], 1e-6f) << i;
  }
  double error2[2] = {0.0, 0.0}, signal2 = 0.0;
  for (const bool non_negative : {false, true}) {
    Output y({1, out, h, w}, false);
    cpu::Int8ConvWorkspace ws;
    cpu::int8_conv2d_forward(Int8Kernels::Emulated, x.ref(),
                             clip / (non_negative ? 255.0f : 127.0f), non_negative, p, 1, false,
                             y.ref(), ws);
    for (std::int64_t o = 0; o < out; ++o)
      for (std::int64_t oy = 0; oy < h; ++oy)
        for (std::int64_t ox = 0; ox < w; ++ox) {
          double exact = bias[static_cast<size_t>(o)];
          for (std::int64_t c = 0; c < in; ++c)
            for (int ky = 0; ky < 3; ++ky)
              for (int kx = 0; kx < 3; ++kx) {
                const std::int64_t iy = oy + ky - 1, ix = ox + kx - 1;
                if (iy < 0 || iy >= h || ix < 0 || ix >= w) continue;
                exact += static_cast<double>(x.values[static_cast<size_t>((c * h + iy) * w + ix)]) *
                         wt[static_cast<size_t>(((o * in + c) * 3 + ky) * 3 + kx)];
              }
          const double d = y.value((o * h + oy) * w + ox) - exact;
          error2[non_negative] += d * d;
          if (!non_negative) signal2 += exact * exact;
        }
  }
  const double signed_rms = std::sqrt(error2[0] / signal2);
  const double unsigned_rms = std::sqrt(error2[1] / signal2);
  std::printf(
      "non-negative input against FP32: relative RMS error, signed mode %.4f%%, non-negative mode "
      "%.4f%%, ratio %.3f (127 / 255 = 0.498)\n",
      100.0 * signed_rms, 100.0 * unsigned_rms, unsigned_rms / signed_rms);
  EXPECT_LT(unsigned_rms / signed_rms, 0.75);
  EXPECT_GT(unsigned_rms / signed_rms, 0.3);
}

}  // namespace
