// --precision bf16 on the CPU (engine/cpu/): the model of the AVX512_BF16 instructions against the
// Intel SDM's definitions; the micro-kernel's convolutions and transposed convolutions against a
// double reference on the same BF16-rounded inputs and prepared weights, at shapes that exercise
// every tail (widths below, at and past 16 and 48 pixels, odd K, column counts past the 8-column
// register tile and the 64-column block), with guard words around the output, independent of the
// thread count; the 16-bit data movement bit for bit the CUDA backend's (emulation); and the whole
// model's BF16 evaluation against its FP32 one and against the CUDA backend's BF16.
//
// Every case runs the micro-kernel on the instruction model (every CPU); where this CPU has
// AVX512_BF16 the same cases run on the real instructions too, and are skipped with the reason
// where it has not.
#include <fmt/format.h>
#include <fmt/ranges.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

#include "core/ops.hpp"
#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "engine/cpu/bf16_conv.hpp"
#include "engine/cpu/half_ops.hpp"
#include "engine/cpu/bf16_isa_emulated.hpp"
#include "engine/cuda/cuda_backend.hpp"
#include "engine/model/op_record.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "tests/support/test_support.hpp"
#include "tests/support/tiny_model.hpp"
#include "weights_io/half.hpp"

using namespace pillarseg;
using cpu::Bf16Kernels;
using cpu::EmulatedBf16Isa;

namespace {

std::uint16_t bf16(float v) {
  return weights::float_to_bf16_bits(v);
}
double value(std::uint16_t bits) {
  return weights::bf16_bits_to_float(bits);
}

std::vector<Bf16Kernels> kernels_to_test() {
  std::vector<Bf16Kernels> list = {Bf16Kernels::Emulated};
  if (cpu::avx512_bf16_available()) list.push_back(Bf16Kernels::Avx512);
  return list;
}
// The Winograd convolution also has its products on AMX tiles (the model, and the instructions
// where this CPU has them).
std::vector<Bf16Kernels> winograd_kernels_to_test() {
  std::vector<Bf16Kernels> list = kernels_to_test();
  list.push_back(Bf16Kernels::AmxEmulated);
  if (cpu::amx_bf16_available()) list.push_back(Bf16Kernels::Amx);
  return list;
}

// ---- the instruction model ----

TEST(EmulatedBf16Isa, ConversionRoundsToNearestEvenAsTheSdmSays) {
  // Normal values: the same as the round-to-nearest-even of weights_io (PyTorch's .bfloat16()).
  Rng rng(5);
  for (int i = 0; i < 10000; ++i) {
    const float v = static_cast<float>(rng.uniform(-1e4, 1e4));
    ASSERT_EQ(EmulatedBf16Isa::float_to_bf16(v), bf16(v)) << v;
  }
  // Ties: 1 + 2^-8 lies halfway between 1 and 1 + 2^-7 and goes to the even 1; 1 + 3 2^-8 to 1 +
  // 2^-6.
  EXPECT_EQ(EmulatedBf16Isa::float_to_bf16(1.0f + 0x1p-8f), 0x3F80);
  EXPECT_EQ(EmulatedBf16Isa::float_to_bf16(1.0f + 3 * 0x1p-8f), 0x3F82);
  // Denormals give a signed zero (VCVTNEPS2BF16 reads them as zero); infinities stay; NaN stays
  // NaN with the quiet bit; the largest finite values round to infinity.
  EXPECT_EQ(EmulatedBf16Isa::float_to_bf16(0x1p-140f), 0x0000);
  EXPECT_EQ(EmulatedBf16Isa::float_to_bf16(-0x1p-140f), 0x8000);
  EXPECT_EQ(EmulatedBf16Isa::float_to_bf16(std::numeric_limits<float>::infinity()), 0x7F80);
  EXPECT_EQ(EmulatedBf16Isa::float_to_bf16(std::bit_cast<float>(0x7F800001u)), 0x7FC0);
  EXPECT_EQ(EmulatedBf16Isa::float_to_bf16(std::numeric_limits<float>::max()), 0x7F80);
}

TEST(EmulatedBf16Isa, DotProductAddsTheOddPairFirstRoundingEachStep) {
  EmulatedBf16Isa::Acc acc{};
  EmulatedBf16Isa::Pair a{}, b{};
  for (int j = 0; j < 16; ++j) {
    acc.v[j] = 1.0f;
    a.v[2 * j] = bf16(2.0f), a.v[2 * j + 1] = bf16(3.0f);
    b.v[2 * j] = bf16(0.5f), b.v[2 * j + 1] = bf16(0.25f);
  }
  acc = EmulatedBf16Isa::dot(acc, a, b);
  EXPECT_EQ(acc.v[0], 2.75f);  // 1 + 3 / 4 + 2 / 2
  // 1 + 2^-24 rounds to 1 (a tie, to even) at each of the two steps: 1, not 1 + 2^-23 as one
  // rounding of the whole sum would give.
  for (int j = 0; j < 16; ++j) {
    acc.v[j] = 1.0f;
    a.v[2 * j] = a.v[2 * j + 1] = bf16(0x1p-12f);
    b.v[2 * j] = b.v[2 * j + 1] = bf16(0x1p-12f);
  }
  acc = EmulatedBf16Isa::dot(acc, a, b);
  EXPECT_EQ(acc.v[3], 1.0f);
  // A denormal BF16 input reads as zero; a denormal result is flushed.
  acc = EmulatedBf16Isa::zero();
  a = EmulatedBf16Isa::broadcast_pair(std::array<std::uint16_t, 2>{0x0001, bf16(1.0f)}.data());
  b = EmulatedBf16Isa::broadcast_pair(
      std::array<std::uint16_t, 2>{bf16(1.0f), bf16(0x1p-70f)}.data());
  acc = EmulatedBf16Isa::dot(acc, a, b);  // 1e-38 * 1 (denormal in, zero) + 1 * 2^-70 = 2^-70
  EXPECT_EQ(acc.v[7], 0x1p-70f);
  b = EmulatedBf16Isa::broadcast_pair(
      std::array<std::uint16_t, 2>{bf16(0x1p-70f), bf16(0x1p-70f)}.data());
  a = EmulatedBf16Isa::broadcast_pair(
      std::array<std::uint16_t, 2>{bf16(0x1p-70f), bf16(0x1p-70f)}.data());
  EXPECT_EQ(EmulatedBf16Isa::dot(EmulatedBf16Isa::zero(), a, b).v[0],
            0.0f);  // 2^-139: denormal -> 0
}

// ---- the AMX tile model ----

using Tiles = cpu::EmulatedAmxTiles;

// A (16 x 32 BF16, row-major) and B (32 x 16 BF16, packed in pairs of rows: row k of the tile is
// (B[2k][n], B[2k + 1][n]) for n = 0..15) through TILELOADD with row strides of their own, C's
// start values, one TDPBF16PS, TILESTORED: C + A B.
std::vector<float> tile_product(const std::vector<float>& a, const std::vector<float>& b,
                                const std::vector<float>& c0) {
  std::vector<std::uint16_t> a_mem(16 * 40), b_mem(16 * 36);  // rows of 40 and 36 words
  for (int m = 0; m < 16; ++m)
    for (int k = 0; k < 32; ++k)
      a_mem[static_cast<size_t>(m * 40 + k)] = bf16(a[static_cast<size_t>(m * 32 + k)]);
  for (int k = 0; k < 32; ++k)
    for (int n = 0; n < 16; ++n)
      b_mem[static_cast<size_t>((k / 2) * 36 + 2 * n + k % 2)] =
          bf16(b[static_cast<size_t>(k * 16 + n)]);
  std::vector<float> c = c0, out(16 * 20, -1.0f);  // stored with rows of 20 floats
  Tiles::load<0>(c.data(), 16 * 4);
  Tiles::load<3>(a_mem.data(), 40 * 2);
  Tiles::load<4>(b_mem.data(), 36 * 2);
  Tiles::dot<0, 3, 4>();
  Tiles::store<0>(out.data(), 20 * 4);
  for (int m = 0; m < 16; ++m) {
    for (int n = 16; n < 20; ++n)
      EXPECT_EQ(out[static_cast<size_t>(m * 20 + n)], -1.0f) << "written past a row";
    for (int n = 0; n < 16; ++n)
      c[static_cast<size_t>(m * 16 + n)] = out[static_cast<size_t>(m * 20 + n)];
  }
  return c;
}

TEST(EmulatedAmxTiles, DotIsTheMatrixProductOfThePairedLayout) {
  // Small integers: every sum exact, whatever the order, so the result is the exact product.
  Rng rng(17);
  std::vector<float> a(16 * 32), b(32 * 16), c0(16 * 16);
  for (float& v : a) v = static_cast<float>(static_cast<int>(rng.uniform(-8, 8)));
  for (float& v : b) v = static_cast<float>(static_cast<int>(rng.uniform(-8, 8)));
  for (float& v : c0) v = static_cast<float>(static_cast<int>(rng.uniform(-100, 100)));
  const std::vector<float> c = tile_product(a, b, c0);
  for (int m = 0; m < 16; ++m) {
    for (int n = 0; n < 16; ++n) {
      double sum = c0[static_cast<size_t>(m * 16 + n)];
      for (int k = 0; k < 32; ++k)
        sum += a[static_cast<size_t>(m * 32 + k)] * b[static_cast<size_t>(k * 16 + n)];
      ASSERT_EQ(c[static_cast<size_t>(m * 16 + n)], sum) << m << ", " << n;
    }
  }
}

TEST(EmulatedAmxTiles, DotAddsTheEvenElementFirstRoundingEachStep) {
  // C = 1, A's pair (1, 1), B's pair (2^24, 1): even first, 1 + 2^24 is a tie that rounds to the
  // even 2^24, then + 1 again: 2^24. (Odd first, as VDPBF16PS goes, would give 1 + 1 + 2^24 =
  // 2^24 + 2.)
  std::vector<float> a(16 * 32, 0.0f), b(32 * 16, 0.0f), c0(16 * 16, 1.0f);
  a[0] = a[1] = 1.0f;
  b[0] = 0x1p24f, b[16] = 1.0f;  // B[0][0], B[1][0]: the pair of column 0
  std::vector<float> c = tile_product(a, b, c0);
  EXPECT_EQ(c[0], 0x1p24f);
  EXPECT_EQ(c[1], 1.0f);  // column 1: zeros added
  // A denormal BF16 input reads as zero, and so does a denormal accumulator; a denormal result is
  // flushed to zero.
  std::fill(a.begin(), a.end(), 0.0f), std::fill(b.begin(), b.end(), 0.0f);
  a[0] = std::bit_cast<float>(0x00010000u), b[0] = 1.0f;  // BF16 0x0001: denormal
  a[1] = 0x1p-70f, b[16] = 0x1p-70f;                      // 2^-140: flushed
  std::fill(c0.begin(), c0.end(), 0x1p-130f);             // a denormal accumulator: zero
  c = tile_product(a, b, c0);
  EXPECT_EQ(c[0], 0.0f);
  EXPECT_EQ(c[5], 0.0f);
}

TEST(CpuBf16Amx, AvailabilityAndTheNativeChoiceAgree) {
  std::string why;
  const bool amx = cpu::amx_bf16_available(&why);
  ::testing::Test::RecordProperty("amx_bf16", amx ? "available" : "not run: " + why);
  EXPECT_EQ(cpu::native_bf16_kernels(), amx ? Bf16Kernels::Amx : Bf16Kernels::Avx512);
  ::setenv("PILLARSEG_CPU_AMX", "0", 1);  // the AVX-512 path alone, asked for
  EXPECT_EQ(cpu::native_bf16_kernels(), Bf16Kernels::Avx512);
  ::unsetenv("PILLARSEG_CPU_AMX");
  if (amx) return;
  EXPECT_FALSE(why.empty());
  // Asked for where it cannot run: an error that says why, not a fault.
  std::vector<std::uint16_t> x(1 * 2 * 4 * 4), w16(2 * 9 * 32);
  std::vector<float> bias(2), y(1 * 2 * 4 * 4);
  cpu::Bf16WinogradWorkspace workspace;
  try {
    cpu::conv3x3_winograd_forward(Bf16Kernels::Amx, HRef{x.data(), {1, 2, 4, 4}},
                                  HRef{w16.data(), {2, 9 * 32}}, nullptr, Ref{bias.data(), {2}},
                                  {2, 2, 3, 3}, false, TensorRef{y.data(), {1, 2, 4, 4}, DType::F32},
                                  workspace);
    FAIL() << "the AMX kernels where the CPU lacks them must throw";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("BF16 convolutions on"), std::string::npos) << e.what();
  }
}

TEST(EmulatedBf16Isa, MaskedLoadsReadOnlyTheirLanes) {
  std::vector<std::uint16_t> x(40);
  for (size_t i = 0; i < x.size(); ++i) x[i] = static_cast<std::uint16_t>(100 + i);
  // Lanes 2..4 of x[10..], lanes 0 and 15 of x[20..].
  const EmulatedBf16Isa::Pair p = EmulatedBf16Isa::load_pairs(x.data(), 10, 0b11100u, 20, 0x8001u);
  for (int i = 0; i < 16; ++i) {
    EXPECT_EQ(p.v[2 * i], i >= 2 && i <= 4 ? 110 + i : 0) << i;
    EXPECT_EQ(p.v[2 * i + 1], i == 0 || i == 15 ? 120 + i : 0) << i;
  }
}

// ---- the convolutions against a double reference ----

struct ConvCase {
  std::int64_t batch, in, height, width, out, kernel;
  int pad;
  bool relu, y_bf16, batchnorm;
};

std::string case_name(const ConvCase& c) {
  return fmt::format("x={}x{}x{}x{},w={}x{}x{}x{},pad={}{}{}{}", c.batch, c.in, c.height, c.width,
                     c.out, c.in, c.kernel, c.kernel, c.pad, c.relu ? ",relu" : "",
                     c.y_bf16 ? ",y=bf16" : ",y=fp32", c.batchnorm ? ",bn" : "");
}

constexpr std::size_t kGuard = 64;
constexpr unsigned char kGuardByte = 0xA5;

// y between guard words: bytes of `n` elements of `element` bytes, the output's first byte at
// data().
struct Guarded {
  std::vector<std::uint8_t> bytes;
  std::size_t payload;
  Guarded(std::int64_t n, std::size_t element)
      : bytes(static_cast<size_t>(n) * element + 2 * kGuard),
        payload(static_cast<size_t>(n) * element) {
    std::memset(bytes.data(), kGuardByte, bytes.size());  // every byte, whatever the size
  }
  void* data() { return bytes.data() + kGuard; }
  // Element i of y, BF16 or FP32.
  double element(size_t i, bool bf16_elements) const {
    if (bf16_elements) {
      std::uint16_t bits;
      std::memcpy(&bits, bytes.data() + kGuard + 2 * i, 2);
      return value(bits);
    }
    float v;
    std::memcpy(&v, bytes.data() + kGuard + 4 * i, 4);
    return v;
  }
  bool intact() const {
    for (size_t i = 0; i < kGuard; ++i) {
      if (bytes[i] != kGuardByte || bytes[kGuard + payload + i] != kGuardByte) return false;
    }
    return true;
  }
};

// Checks y against the double reference: |y - ref| <= bound + |ref| 2^-8 when y is BF16 (its
// rounding, half an ulp of 2^-7) + 1e-30, ref through the ReLU where relu is set.
void expect_within(const std::vector<double>& ref, const std::vector<double>& bound,
                   const Guarded& y, bool y_bf16, bool relu, const std::string& what) {
  ASSERT_TRUE(y.intact()) << what << ": wrote outside y";
  int64_t bad = 0;
  for (size_t i = 0; i < ref.size(); ++i) {
    const double got = y.element(i, y_bf16);
    const double expected = relu ? std::max(ref[i], 0.0) : ref[i];
    const double tolerance = bound[i] + (y_bf16 ? 0x1p-8 * std::abs(expected) : 0.0) + 1e-30;
    if (!(std::abs(got - expected) <= tolerance) && bad++ < 5) {
      ADD_FAILURE() << what << ": element " << i << " is " << got << ", expected " << expected
                    << " +- " << tolerance;
    }
  }
  EXPECT_EQ(bad, 0) << what;
}

// The direct convolutions' bound: (K + 2) 2^-24 sum |terms| (the FP32 sums, one rounding per
// term).
void expect_close(const std::vector<double>& ref, const std::vector<double>& magnitude,
                  const Guarded& y, bool y_bf16, std::int64_t k, bool relu,
                  const std::string& what) {
  std::vector<double> bound(magnitude.size());
  for (size_t i = 0; i < bound.size(); ++i)
    bound[i] = static_cast<double>(k + 2) * 0x1p-24 * magnitude[i];
  expect_within(ref, bound, y, y_bf16, relu, what);
}

// Says in the test's properties why the AVX-512 instructions did not run, where they did not.
void record_where_not_native() {
  std::string why;
  if (!cpu::avx512_bf16_available(&why))
    ::testing::Test::RecordProperty("avx512_bf16", "not run: " + why);
}

std::vector<float> random_floats(std::int64_t n, Rng& rng, double lo = -1, double hi = 1) {
  std::vector<float> v(static_cast<size_t>(n));
  for (float& f : v) f = static_cast<float>(rng.uniform(lo, hi));
  return v;
}

class CpuBf16Conv : public ::testing::TestWithParam<ConvCase> {};

TEST_P(CpuBf16Conv, MatchesTheDoubleReference) {
  const ConvCase c = GetParam();
  Rng rng(31);
  const std::int64_t kk = c.kernel * c.kernel, k = c.in * kk;
  const std::int64_t ho = c.height + 2 * c.pad - c.kernel + 1,
                     wo = c.width + 2 * c.pad - c.kernel + 1;
  std::vector<float> w = random_floats(c.out * k, rng), bias = random_floats(c.out, rng);
  std::vector<float> gamma = random_floats(c.out, rng, 0.5, 1.5), beta = random_floats(c.out, rng),
                     mean = random_floats(c.out, rng), var = random_floats(c.out, rng, 0.5, 2.0);
  std::vector<float> xf = random_floats(c.batch * c.in * c.height * c.width, rng, -2, 2);
  const Shape weight = {c.out, c.in, c.kernel, c.kernel};
  std::vector<std::uint16_t> w16(
      static_cast<size_t>(shape_numel(op::half16_conv_weights(weight, false))));
  std::vector<float> bias_out(static_cast<size_t>(c.out));
  Ref w_ref{w.data(), weight}, b_ref{bias.data(), {c.out}};
  BatchNormRefs bn;
  bn.gamma = {gamma.data(), {c.out}}, bn.beta = {beta.data(), {c.out}};
  bn.running_mean = {mean.data(), {c.out}}, bn.running_var = {var.data(), {c.out}};
  HRef w16_ref{w16.data(), op::half16_conv_weights(weight, false)};
  Ref bias_out_ref{bias_out.data(), {c.out}};
  cpu::prepare_conv_weights(w_ref, &b_ref, c.batchnorm ? &bn : nullptr, Precision::BF16, w16_ref,
                            bias_out_ref);
  // The folding: w' = bf16(w gamma / sqrt(var + eps)), b' = scale b + beta - scale mean, in
  // column t Ip + i of row o (tap-major, the channels padded with zeros to Ip).
  const std::int64_t kp = w16_ref.dim(1), padded = kp / kk;
  ASSERT_EQ(padded, (c.in + 31) / 32 * 32);
  for (std::int64_t o = 0; o < c.out; ++o) {
    const float scale = c.batchnorm ? gamma[o] / std::sqrt(var[o] + bn.eps) : 1.0f;
    for (std::int64_t t = 0; t < kk; ++t) {
      for (std::int64_t i = 0; i < padded; ++i) {
        ASSERT_EQ(w16[static_cast<size_t>(o * kp + t * padded + i)],
                  i < c.in ? bf16(w[static_cast<size_t>((o * c.in + i) * kk + t)] * scale) : 0)
            << "row " << o << " tap " << t << " channel " << i;
      }
    }
    const float shift = c.batchnorm ? beta[o] - scale * mean[o] : 0.0f;
    ASSERT_EQ(bias_out[static_cast<size_t>(o)], scale * bias[o] + shift);
  }
  std::vector<std::uint16_t> x16(xf.size());
  HRef x_ref{x16.data(), {c.batch, c.in, c.height, c.width}};
  cpu::to_half(Ref{xf.data(), x_ref.shape}, Precision::BF16, x_ref);
  // The reference in double on the rounded values.
  std::vector<double> ref(static_cast<size_t>(c.batch * c.out * ho * wo)), magnitude(ref.size());
  for (std::int64_t b = 0; b < c.batch; ++b) {
    for (std::int64_t o = 0; o < c.out; ++o) {
      for (std::int64_t y = 0; y < ho; ++y) {
        for (std::int64_t xx = 0; xx < wo; ++xx) {
          double sum = bias_out[static_cast<size_t>(o)], mag = std::abs(sum);
          for (std::int64_t i = 0; i < c.in; ++i) {
            for (std::int64_t ky = 0; ky < c.kernel; ++ky) {
              for (std::int64_t kx = 0; kx < c.kernel; ++kx) {
                const std::int64_t iy = y + ky - c.pad, ix = xx + kx - c.pad;
                if (iy < 0 || iy >= c.height || ix < 0 || ix >= c.width) continue;
                const double term =
                    value(w16[static_cast<size_t>(o * kp + (ky * c.kernel + kx) * padded + i)]) *
                    value(
                        x16[static_cast<size_t>(((b * c.in + i) * c.height + iy) * c.width + ix)]);
                sum += term, mag += std::abs(term);
              }
            }
          }
          const size_t at = static_cast<size_t>(((b * c.out + o) * ho + y) * wo + xx);
          ref[at] = sum, magnitude[at] = mag;
        }
      }
    }
  }
  for (const Bf16Kernels kernels : kernels_to_test()) {
    std::vector<std::vector<std::uint8_t>> by_threads;
    for (const int threads : {1, 2}) {
      ScopedThreads scoped(threads);
      Guarded y(static_cast<std::int64_t>(ref.size()), c.y_bf16 ? 2 : 4);
      const TensorRef y_ref{y.data(), {c.batch, c.out, ho, wo}, c.y_bf16 ? DType::BF16 : DType::F32};
      cpu::conv2d_forward(kernels, x_ref, w16_ref, bias_out_ref, weight, c.pad, c.relu, y_ref);
      expect_close(ref, magnitude, y, c.y_bf16, k, c.relu,
                   std::string(cpu::bf16_kernels_name(kernels)) + " " + std::to_string(threads) +
                       " threads");
      by_threads.push_back(y.bytes);
    }
    EXPECT_EQ(by_threads[0], by_threads[1]) << "the thread count changed the result";
  }
  record_where_not_native();
}

INSTANTIATE_TEST_SUITE_P(
    Shapes, CpuBf16Conv,
    ::testing::Values(
        ConvCase{1, 3, 5, 7, 5, 3, 1, true, false, true},     // odd K, width < 16, 5 columns
        ConvCase{2, 16, 9, 37, 13, 3, 1, false, true, true},  // 3 vectors, 8 + 5 columns
        ConvCase{1, 8, 4, 50, 20, 1, 0, true, true, false},   // 1 x 1, 48 + 2 pixels
        ConvCase{1, 5, 6, 6, 9, 3, 0, false, false, false},   // no padding
        ConvCase{1, 7, 3, 17, 70, 3, 1, true, false, true},   // two column blocks
        ConvCase{1, 4, 2, 16, 8, 3, 1, false, true, false},   // exactly one vector
        ConvCase{1, 37, 4, 9, 6, 3, 1, true, false, true}),   // channels past one step of 32, odd
    [](const ::testing::TestParamInfo<ConvCase>& param) {
      std::string s = case_name(param.param);
      for (char& ch : s)
        if (!std::isalnum(static_cast<unsigned char>(ch))) ch = '_';
      return s;
    });

struct TransposedCase {
  std::int64_t batch, in, height, width, out;
  bool y_bf16;
};

class CpuBf16ConvTranspose : public ::testing::TestWithParam<TransposedCase> {};

TEST_P(CpuBf16ConvTranspose, MatchesTheDoubleReference) {
  const TransposedCase c = GetParam();
  Rng rng(47);
  const Shape weight = {c.in, c.out, 2, 2};
  std::vector<float> w = random_floats(c.in * c.out * 4, rng), bias = random_floats(c.out, rng);
  std::vector<float> xf = random_floats(c.batch * c.in * c.height * c.width, rng, -2, 2);
  const Shape w16_shape = op::half16_conv_weights(weight, true);
  std::vector<std::uint16_t> w16(static_cast<size_t>(shape_numel(w16_shape)));
  std::vector<float> bias_out(static_cast<size_t>(4 * c.out));
  HRef w16_ref{w16.data(), w16_shape};
  Ref bias_out_ref{bias_out.data(), {4 * c.out}}, b_ref{bias.data(), {c.out}};
  cpu::prepare_conv_transpose_weights(Ref{w.data(), weight}, &b_ref, Precision::BF16, w16_ref,
                                      bias_out_ref);
  std::vector<std::uint16_t> x16(xf.size());
  HRef x_ref{x16.data(), {c.batch, c.in, c.height, c.width}};
  cpu::to_half(Ref{xf.data(), x_ref.shape}, Precision::BF16, x_ref);
  const std::int64_t oh = 2 * c.height, ow = 2 * c.width;
  std::vector<double> ref(static_cast<size_t>(c.batch * c.out * oh * ow)), magnitude(ref.size());
  for (std::int64_t b = 0; b < c.batch; ++b) {
    for (std::int64_t o = 0; o < c.out; ++o) {
      for (std::int64_t y = 0; y < oh; ++y) {
        for (std::int64_t xx = 0; xx < ow; ++xx) {
          double sum = bias[static_cast<size_t>(o)], mag = std::abs(sum);
          for (std::int64_t i = 0; i < c.in; ++i) {
            const double term =
                value(bf16(w[static_cast<size_t>(((i * c.out + o) * 2 + y % 2) * 2 + xx % 2)])) *
                value(x16[static_cast<size_t>(((b * c.in + i) * c.height + y / 2) * c.width +
                                              xx / 2)]);
            sum += term, mag += std::abs(term);
          }
          const size_t at = static_cast<size_t>(((b * c.out + o) * oh + y) * ow + xx);
          ref[at] = sum, magnitude[at] = mag;
        }
      }
    }
  }
  for (const Bf16Kernels kernels : kernels_to_test()) {
    Guarded y(static_cast<std::int64_t>(ref.size()), c.y_bf16 ? 2 : 4);
    cpu::conv_transpose2d_forward(kernels, x_ref, w16_ref, bias_out_ref, weight,
                                   TensorRef{y.data(), {c.batch, c.out, oh, ow}, c.y_bf16 ? DType::BF16 : DType::F32});
    expect_close(ref, magnitude, y, c.y_bf16, c.in, false, cpu::bf16_kernels_name(kernels));
  }
}

INSTANTIATE_TEST_SUITE_P(
    Shapes, CpuBf16ConvTranspose,
    ::testing::Values(TransposedCase{1, 3, 3, 5, 3, false},    // odd K, 12 columns
                      TransposedCase{2, 8, 4, 20, 2, true},    // 2 vectors, 8 columns
                      TransposedCase{1, 16, 2, 49, 17, true},  // 68 columns, 4 vectors
                      TransposedCase{1, 6, 1, 16, 1, false}),
    [](const ::testing::TestParamInfo<TransposedCase>& param) {
      const TransposedCase& c = param.param;
      return fmt::format("x_{}x{}x{}x{}_o{}_{}", c.batch, c.in, c.height, c.width, c.out,
                         c.y_bf16 ? "bf16" : "fp32");
    });

TEST(CpuBf16Conv, WrongShapesAndPrecisionsSayWhat) {
  std::vector<std::uint16_t> x(2 * 3 * 4 * 4), w16(4 * 9 * 32);
  std::vector<float> bias(4), y(2 * 4 * 4 * 4);
  const HRef x_ref{x.data(), {2, 3, 4, 4}};
  const Ref bias_ref{bias.data(), {4}};
  try {
    cpu::conv2d_forward(Bf16Kernels::Emulated, x_ref, HRef{w16.data(), {4, 288}}, bias_ref,
                        {4, 3, 3, 3}, 1, false, TensorRef{y.data(), {2, 4, 4, 5}, DType::F32});
    FAIL() << "a wrong y shape must throw";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("CpuBackend::conv2d_prepared_forward: y must be (2, 4, 4, 4)"),
              std::string::npos)
        << e.what();
  }
  try {
    cpu::conv2d_forward(Bf16Kernels::Emulated, x_ref, HRef{w16.data(), {4, 27}}, bias_ref,
                        {4, 3, 3, 3}, 1, false, TensorRef{y.data(), {2, 4, 4, 4}, DType::F32});
    FAIL() << "unpadded weights must throw";
  } catch (const Error& e) {
    // 9 taps of the 3 channels padded to 32 (tap-major).
    EXPECT_NE(std::string(e.what()).find("w16 must be (4, 288)"), std::string::npos) << e.what();
  }
  auto backend = make_cpu_backend();
  std::string why;
  EXPECT_FALSE(backend->supports_precision(Precision::F16, &why));
  EXPECT_NE(why.find("no FP16 convolutions"), std::string::npos) << why;
  EXPECT_FALSE(make_cpu_reference_backend()->supports_precision(Precision::BF16, &why));
  EXPECT_NE(why.find("FP32 only"), std::string::npos) << why;
  EXPECT_TRUE(make_cpu_backend_emulated_bf16()->supports_precision(Precision::BF16));
  // Native BF16 exactly where the CPU has AVX512_BF16; else the reason names what is missing.
  const bool native = backend->supports_precision(Precision::BF16, &why);
  EXPECT_EQ(native, cpu::avx512_bf16_available());
  if (!native) {
    EXPECT_NE(why.find("need AVX512_BF16"), std::string::npos) << why;
  }
}

// ---- the 3 x 3 convolutions by Winograd F(2x2, 3x3) ----

struct WinogradCase {
  std::int64_t batch, in, height, width, out;
  bool relu, y_bf16;
};

// The Winograd convolution against the double reference of the direct one on the same BF16 x
// and prepared kernels g. Tolerance, per output: the rounding of U = G g G^T and of V = B^T d B
// to BF16 (2^-8 each, the FP32 transform of V adding 3 2^-24), the FP32 sums over the C channels
// (C + 8 roundings of 2^-24 in the dot products and the output transform), all relative to S =
// sum_c sum_p |a_p| |U_p| |V_p| (a_p the output transform's coefficient of position p for this
// output, U and V exact, in double); plus half an ulp of BF16 (2^-8 |y|) when y is BF16. Then:
// bit for bit the same on the instruction model and the AVX-512 instructions and for 1 and 2
// threads; nothing written outside y.
class CpuBf16Winograd : public ::testing::TestWithParam<WinogradCase> {};

TEST_P(CpuBf16Winograd, MatchesTheDoubleReference) {
  const WinogradCase c = GetParam();
  Rng rng(53);
  const Shape weight = {c.out, c.in, 3, 3};
  std::vector<float> w = random_floats(c.out * c.in * 9, rng), bias = random_floats(c.out, rng);
  std::vector<float> xf = random_floats(c.batch * c.in * c.height * c.width, rng, -2, 2);
  std::vector<std::uint16_t> w16(
      static_cast<size_t>(shape_numel(op::half16_conv_weights(weight, false))));
  std::vector<float> bias_out(static_cast<size_t>(c.out));
  HRef w16_ref{w16.data(), op::half16_conv_weights(weight, false)};
  Ref bias_out_ref{bias_out.data(), {c.out}}, b_ref{bias.data(), {c.out}};
  cpu::prepare_conv_weights(Ref{w.data(), weight}, &b_ref, nullptr, Precision::BF16, w16_ref,
                            bias_out_ref);
  std::vector<std::uint16_t> x16(xf.size());
  HRef x_ref{x16.data(), {c.batch, c.in, c.height, c.width}};
  cpu::to_half(Ref{xf.data(), x_ref.shape}, Precision::BF16, x_ref);
  const std::int64_t kp = w16_ref.dim(1), H = c.height, W = c.width;
  const auto g = [&](std::int64_t o, std::int64_t i, int ky, int kx) {
    return value(w16[static_cast<size_t>(o * kp + (ky * 3 + kx) * (kp / 9) + i)]);
  };
  const auto xv = [&](std::int64_t b, std::int64_t i, std::int64_t y, std::int64_t x) {
    if (y < 0 || y >= H || x < 0 || x >= W) return 0.0;
    return value(x16[static_cast<size_t>(((b * c.in + i) * H + y) * W + x)]);
  };
  // The exact transforms, for the tolerance.
  const double G[4][3] = {{1, 0, 0}, {0.5, 0.5, 0.5}, {0.5, -0.5, 0.5}, {0, 0, 1}};
  const double BT[4][4] = {{1, 0, -1, 0}, {0, 1, 1, 0}, {0, -1, 1, 0}, {0, 1, 0, -1}};
  const double AT[2][4] = {{1, 1, 1, 0}, {0, 1, -1, -1}};
  std::vector<double> u(static_cast<size_t>(c.out * c.in * 16));
  for (std::int64_t o = 0; o < c.out; ++o) {
    for (std::int64_t i = 0; i < c.in; ++i) {
      for (int p = 0; p < 16; ++p) {
        double sum = 0;
        for (int a = 0; a < 3; ++a)
          for (int bb = 0; bb < 3; ++bb) sum += G[p / 4][a] * g(o, i, a, bb) * G[p % 4][bb];
        u[static_cast<size_t>((o * c.in + i) * 16 + p)] = sum;
      }
    }
  }
  std::vector<double> ref(static_cast<size_t>(c.batch * c.out * H * W)), bound(ref.size());
  for (std::int64_t b = 0; b < c.batch; ++b) {
    for (std::int64_t ty = 0; ty < (H + 1) / 2; ++ty) {
      for (std::int64_t tx = 0; tx < (W + 1) / 2; ++tx) {
        std::vector<double> v(static_cast<size_t>(c.in * 16));
        for (std::int64_t i = 0; i < c.in; ++i) {
          for (int p = 0; p < 16; ++p) {
            double sum = 0;
            for (int r = 0; r < 4; ++r)
              for (int q = 0; q < 4; ++q)
                sum += BT[p / 4][r] * xv(b, i, 2 * ty - 1 + r, 2 * tx - 1 + q) * BT[p % 4][q];
            v[static_cast<size_t>(i * 16 + p)] = sum;
          }
        }
        for (std::int64_t o = 0; o < c.out; ++o) {
          for (int e = 0; e < 4; ++e) {
            const std::int64_t y = 2 * ty + e / 2, x = 2 * tx + e % 2;
            if (y >= H || x >= W) continue;
            double sum = bias_out[static_cast<size_t>(o)], s = 0;
            for (std::int64_t i = 0; i < c.in; ++i) {
              for (int ky = 0; ky < 3; ++ky)
                for (int kx = 0; kx < 3; ++kx)
                  sum += g(o, i, ky, kx) * xv(b, i, y + ky - 1, x + kx - 1);
              for (int p = 0; p < 16; ++p) {
                s += std::abs(AT[e / 2][p / 4] * AT[e % 2][p % 4]) *
                     std::abs(u[static_cast<size_t>((o * c.in + i) * 16 + p)]) *
                     std::abs(v[static_cast<size_t>(i * 16 + p)]);
              }
            }
            const size_t at = static_cast<size_t>(((b * c.out + o) * H + y) * W + x);
            ref[at] = c.relu ? std::max(sum, 0.0) : sum;
            bound[at] = (2 * 0x1p-8 + 0x1p-16 + static_cast<double>(c.in + 8) * 0x1p-24) * s;
          }
        }
      }
    }
  }
  // The results of each kernel set, for 1 and 2 threads.
  std::vector<std::pair<Bf16Kernels, std::vector<std::uint8_t>>> results;
  for (const Bf16Kernels kernels : winograd_kernels_to_test()) {
    for (const int threads : {1, 2}) {
      ScopedThreads scoped(threads);
      const std::string what = std::string(cpu::bf16_kernels_name(kernels)) + ", " +
                               std::to_string(threads) + " threads";
      Guarded y(static_cast<std::int64_t>(ref.size()), c.y_bf16 ? 2 : 4);
      cpu::Bf16WinogradWorkspace workspace;
      cpu::conv3x3_winograd_forward(kernels, x_ref, w16_ref, nullptr, bias_out_ref, weight, c.relu,
                                    TensorRef{y.data(), {c.batch, c.out, H, W}, c.y_bf16 ? DType::BF16 : DType::F32}, workspace);
      expect_within(ref, bound, y, c.y_bf16, false, what);
      // The same with the transformed weights made beforehand (as the model makes them once):
      // the same bits.
      std::vector<std::uint16_t> u16(
          static_cast<size_t>(cpu::winograd_weight_elements(kernels, weight)));
      cpu::winograd_transform_weights(kernels, w16_ref, weight, u16.data());
      Guarded y_prepared(static_cast<std::int64_t>(ref.size()), c.y_bf16 ? 2 : 4);
      cpu::conv3x3_winograd_forward(
          kernels, x_ref, w16_ref, u16.data(), bias_out_ref, weight, c.relu,
          TensorRef{y_prepared.data(), {c.batch, c.out, H, W}, c.y_bf16 ? DType::BF16 : DType::F32}, workspace);
      EXPECT_EQ(y_prepared.bytes, y.bytes) << what << ": with U made beforehand";
      results.emplace_back(kernels, y.bytes);
    }
  }
  // The thread count changes nothing; the AVX-512 instructions give their model's bits. The AMX
  // path sums in another order (bf16_amx.hpp): held to the bound above, not to these bits.
  const auto bits = [&](Bf16Kernels kernels, int threads) {
    for (size_t r = 0; r < results.size(); r += 2)
      if (results[r].first == kernels) return &results[r + (threads == 2 ? 1 : 0)].second;
    return static_cast<std::vector<std::uint8_t>*>(nullptr);
  };
  for (const Bf16Kernels kernels : winograd_kernels_to_test()) {
    EXPECT_EQ(*bits(kernels, 2), *bits(kernels, 1))
        << cpu::bf16_kernels_name(kernels) << ": 2 threads differ";
  }
  if (bits(Bf16Kernels::Avx512, 1) != nullptr) {
    EXPECT_EQ(*bits(Bf16Kernels::Avx512, 1), *bits(Bf16Kernels::Emulated, 1))
        << "the instructions differ from their model";
  }
  record_where_not_native();
}

INSTANTIATE_TEST_SUITE_P(
    Shapes, CpuBf16Winograd,
    ::testing::Values(
        WinogradCase{1, 3, 5, 7, 5, true, false},       // odd H, W and C; one partial vector
        WinogradCase{2, 16, 9, 37, 13, false, true},    // 5 x 19 tiles: rows of 19, 8 + 5 columns
        WinogradCase{1, 257, 9, 37, 9, true, true},     // 48-tile blocks: two, runs across rows
        WinogradCase{1, 8, 2, 66, 8, false, false},     // one tile row of 33: 16 + 16 + 1 tiles
        WinogradCase{1, 4, 1, 1, 3, false, false},      // one pixel
        WinogradCase{1, 6, 12, 100, 17, true, false}),  // 300 tiles, 8 + 8 + 1 columns
    [](const ::testing::TestParamInfo<WinogradCase>& param) {
      const WinogradCase& c = param.param;
      return fmt::format("x_{}x{}x{}x{}_o{}{}_y_{}", c.batch, c.in, c.height, c.width, c.out,
                         c.relu ? "_relu" : "", c.y_bf16 ? "bf16" : "fp32");
    });

// ---- the 16-bit data movement, bit for bit the CUDA backend's ----

// Uploads `host` to `be`, runs `op`, downloads n elements of the output.
template <class T>
struct Device {
  Backend& be;
  std::vector<void*> blocks;
  ~Device() {
    for (void* b : blocks) be.deallocate(b);
  }
  T* put(const std::vector<T>& host) {
    void* p = be.allocate(host.size() * sizeof(T));
    be.upload(p, host.data(), host.size() * sizeof(T));
    blocks.push_back(p);
    return static_cast<T*>(p);
  }
  std::vector<T> get(const T* p, std::int64_t n) {
    std::vector<T> host(static_cast<size_t>(n));
    be.download(host.data(), p, host.size() * sizeof(T));
    return host;
  }
};

std::vector<std::uint16_t> run_half_ops(Backend& be, const std::vector<float>& xf,
                                        const Shape& shape) {
  Device<std::uint16_t> d{be, {}};
  Device<float> f{be, {}};
  const std::int64_t n = shape_numel(shape);
  float* xd = f.put(xf);
  HRef h{d.put(std::vector<std::uint16_t>(static_cast<size_t>(n))), shape};
  const auto bf16 = [](const HRef& r) { return TensorRef{r.data, r.shape, DType::BF16}; };
  be.convert(Ref{xd, shape}, bf16(h));
  const Shape pooled_shape = op::maxpool2d(shape);
  HRef pooled{d.put(std::vector<std::uint16_t>(static_cast<size_t>(shape_numel(pooled_shape)))),
              pooled_shape};
  be.maxpool2d_forward(bf16(h), bf16(pooled), nullptr);
  const Shape up_shape = op::upsample_bilinear(pooled_shape);
  HRef up{d.put(std::vector<std::uint16_t>(static_cast<size_t>(shape_numel(up_shape)))), up_shape};
  be.upsample_bilinear_forward(bf16(pooled), bf16(up));
  const Shape cat_shape = op::pad_concat(h.shape, up.shape);
  HRef cat{d.put(std::vector<std::uint16_t>(static_cast<size_t>(shape_numel(cat_shape)))),
           cat_shape};
  be.pad_concat_forward(bf16(h), bf16(up), bf16(cat));
  const Shape wide_shape = {shape[0], cat_shape[1] + 3, shape[2], shape[3]};
  HRef wide{d.put(std::vector<std::uint16_t>(static_cast<size_t>(shape_numel(wide_shape)), 0x1234)),
            wide_shape};
  be.copy_channels(bf16(cat), 2, bf16(wide));
  std::vector<std::uint16_t> all = d.get(h.data, n);
  for (const HRef* r : {&pooled, &up, &cat, &wide}) {
    const std::vector<std::uint16_t> part = d.get(r->data, r->numel());
    all.insert(all.end(), part.begin(), part.end());
  }
  return all;
}

TEST(CpuHalfOps, BitForBitTheCudaBackends) {
  Rng rng(9);
  const Shape shape = {2, 3, 9, 13};  // odd sizes: the pooled map is padded back
  std::vector<float> xf = random_floats(shape_numel(shape), rng, -3, 3);
  xf[5] = std::numeric_limits<float>::quiet_NaN();  // NaN wins the max-pool, as in FP32
  auto cpu_backend = make_cpu_backend_emulated_bf16();
  CudaBackend cuda_backend;
  const std::vector<std::uint16_t> on_cpu = run_half_ops(*cpu_backend, xf, shape);
  const std::vector<std::uint16_t> on_cuda = run_half_ops(cuda_backend, xf, shape);
  EXPECT_EQ(on_cpu, on_cuda);
  // And they are what they should be: the copy keeps the band's neighbours.
  EXPECT_EQ(on_cpu.back(), 0x1234);
  EXPECT_EQ(on_cpu[0], bf16(xf[0]));
}

// The scatter into a 16-bit canvas band (channels 2..4 of 6, batch 2, 5 x 7 cells): the band's
// values are the FP32 scatter's rounded (what convert makes of its canvas), the other channels
// keep 0x1234, an inert row (-1, -1, -1) is skipped; the CPU's bits are the CUDA backend's.
std::vector<std::uint16_t> run_half_scatter(Backend& be) {
  Rng rng(17);
  const std::int64_t pillars = 9, c = 3, b = 2, h = 5, w = 7, cc = 6;
  const int channel0 = 2;
  std::vector<std::int32_t> cells;
  for (std::int64_t p = 0; p < pillars; ++p) {  // distinct cells
    cells.push_back(static_cast<std::int32_t>(p % b));
    cells.push_back(static_cast<std::int32_t>(p % h));
    cells.push_back(static_cast<std::int32_t>((3 * p) % w));
  }
  const std::vector<float> features = random_floats(pillars * c, rng, -3, 3);
  Device<float> f{be, {}};
  Device<std::int32_t> i{be, {}};
  Device<std::uint16_t> d{be, {}};
  const Shape canvas_shape = {b, cc, h, w};
  const std::int64_t n = shape_numel(canvas_shape);
  // FP32: the valid rows, then rounded.
  Ref canvas32{f.put(std::vector<float>(static_cast<size_t>(n), 0.0f)), canvas_shape};
  be.scatter_forward(Ref{f.put(features), {pillars, c}}, IRef{i.put(cells), {pillars, 3}}, channel0,
                     canvas32);
  HRef rounded{d.put(std::vector<std::uint16_t>(static_cast<size_t>(n))), canvas_shape};
  be.convert(canvas32, TensorRef{rounded.data, rounded.shape, DType::BF16});
  // 16-bit, with an inert row appended.
  std::vector<float> more = features;
  more.insert(more.end(), {7.0f, 7.0f, 7.0f});
  std::vector<std::int32_t> more_cells = cells;
  more_cells.insert(more_cells.end(), {-1, -1, -1});
  HRef canvas16{d.put(std::vector<std::uint16_t>(static_cast<size_t>(n), 0x1234)), canvas_shape};
  be.scatter_forward(Ref{f.put(more), {pillars + 1, c}}, IRef{i.put(more_cells), {pillars + 1, 3}}, channel0,
                     TensorRef{canvas16.data, canvas16.shape, DType::BF16});
  const std::vector<std::uint16_t> expected = d.get(rounded.data, n), got = d.get(canvas16.data, n);
  for (std::int64_t e = 0; e < n; ++e) {
    const std::int64_t channel = e / (h * w) % cc;
    const bool in_band = channel >= channel0 && channel < channel0 + c;
    EXPECT_EQ(got[static_cast<size_t>(e)], in_band ? expected[static_cast<size_t>(e)] : 0x1234)
        << be.name() << ", element " << e;
  }
  return got;
}

TEST(CpuHalfOps, ScatterIsTheFp32ScatterRoundedBitForBitTheCudaBackends) {
  auto cpu_backend = make_cpu_backend_emulated_bf16();
  CudaBackend cuda_backend;
  EXPECT_EQ(run_half_scatter(*cpu_backend), run_half_scatter(cuda_backend));
}

// The CPU's 16-bit scatter splits the channels between threads: a cell named by several pillars
// still holds the last one's value in every channel (the FP32 scatter's order), out-of-range
// rows write nothing, and channels outside the band keep their contents.
TEST(CpuHalfOps, ScatterKeepsTheLastPillarOfARepeatedCellInEveryChannel) {
  auto be = make_cpu_backend_emulated_bf16();
  const std::int64_t c = 7, b = 1, h = 3, w = 5, cc = 9;
  const int channel0 = 1;
  // Pillars 0, 2 and 3 name cell (0, 1, 2); pillar 1 names (0, 2, 4); pillar 4 is off the grid.
  const std::vector<std::int32_t> cells = {0, 1, 2, 0, 2, 4, 0, 1, 2, 0, 1, 2, 0, 3, 0};
  std::vector<float> features(static_cast<size_t>(5 * c));
  for (std::int64_t r = 0; r < 5; ++r)
    for (std::int64_t k = 0; k < c; ++k)
      features[static_cast<size_t>(r * c + k)] = static_cast<float>(10 * (r + 1) + k);  // exact in BF16
  Device<float> f{*be, {}};
  Device<std::int32_t> i{*be, {}};
  Device<std::uint16_t> d{*be, {}};
  const Shape canvas_shape = {b, cc, h, w};
  const std::int64_t n = shape_numel(canvas_shape), plane = h * w;
  HRef canvas{d.put(std::vector<std::uint16_t>(static_cast<size_t>(n), 0x1234)), canvas_shape};
  be->scatter_forward(Ref{f.put(features), {5, c}}, IRef{i.put(cells), {5, 3}}, channel0,
                      TensorRef{canvas.data, canvas.shape, DType::BF16});
  const std::vector<std::uint16_t> got = d.get(canvas.data, n);
  const auto bits = [](float v) { return static_cast<std::uint16_t>(std::bit_cast<std::uint32_t>(v) >> 16); };
  for (std::int64_t e = 0; e < n; ++e) {
    const std::int64_t channel = e / plane, cell = e % plane, k = channel - channel0;
    std::uint16_t expected = 0x1234;
    if (k >= 0 && k < c) {
      expected = 0;
      if (cell == 1 * w + 2) expected = bits(static_cast<float>(40 + k));  // pillar 3, the last
      if (cell == 2 * w + 4) expected = bits(static_cast<float>(20 + k));  // pillar 1
    }
    EXPECT_EQ(got[static_cast<size_t>(e)], expected) << "channel " << channel << ", cell " << cell;
  }
}

// ---- FP32 arithmetic on BF16 activations ----

// FP32 prepared weights (Backend::prepared_conv_dtype): the eval BatchNorm folded into FP32
// weights, the FP32 Winograd F(4x4, 3x3) reading the BF16 x and writing the BF16 y: against the
// double reference of the direct convolution on the widened x with the unfolded weights and the
// BatchNorm after it, within the FP32 sums' error (relative 1e-5 of sum |w s x|) plus half an ulp
// of the BF16 output; and on F32 x and y, the same convolution unrounded.
TEST(CpuBf16Network, Fp32PreparedWeightsRunTheFp32WinogradOnBf16Activations) {
  const std::int64_t B = 2, I = 5, H = 9, W = 7, O = 6;
  Rng rng(71);
  std::vector<float> xf = random_floats(B * I * H * W, rng, -2, 2), w = random_floats(O * I * 9, rng, -0.5, 0.5),
                     bias = random_floats(O, rng), gamma = random_floats(O, rng, 0.5, 1.5),
                     beta = random_floats(O, rng), mean = random_floats(O, rng), var = random_floats(O, rng, 0.5, 2);
  std::vector<std::uint16_t> x(xf.size());
  for (size_t i = 0; i < xf.size(); ++i) x[i] = bf16(xf[i]), xf[i] = static_cast<float>(value(x[i]));
  const float eps = 1e-5f;
  const Shape weight = {O, I, 3, 3};
  auto backend = make_cpu_backend_emulated_bf16();
  EXPECT_EQ(backend->prepared_conv_transform_elements(weight, 1, DType::F32), 0);
  std::vector<float> prepared(w.size()), bias_out(O);
  Ref prepared_bias{bias_out.data(), {O}};
  const Ref bias_ref{bias.data(), {O}};
  BatchNormRefs bn;
  bn.gamma = {gamma.data(), {O}}, bn.beta = {beta.data(), {O}};
  bn.running_mean = {mean.data(), {O}}, bn.running_var = {var.data(), {O}}, bn.eps = eps;
  const TensorRef prepared_ref{prepared.data(), weight, DType::F32};
  backend->prepare_conv_weights(Ref{w.data(), weight}, &bias_ref, &bn, prepared_ref, prepared_bias, TensorRef{});
  std::vector<std::uint16_t> y(static_cast<size_t>(B * O * H * W), 0x7FC1);
  std::vector<float> yf(y.size());
  backend->conv2d_prepared_forward(TensorRef{x.data(), {B, I, H, W}, DType::BF16}, prepared_ref, TensorRef{},
                                   prepared_bias, weight, 1, true, TensorRef{y.data(), {B, O, H, W}, DType::BF16});
  backend->conv2d_prepared_forward(TensorRef{xf.data(), {B, I, H, W}, DType::F32}, prepared_ref, TensorRef{},
                                   prepared_bias, weight, 1, true, TensorRef{yf.data(), {B, O, H, W}, DType::F32});
  for (std::int64_t b = 0; b < B; ++b)
    for (std::int64_t o = 0; o < O; ++o) {
      const double s = gamma[o] / std::sqrt(static_cast<double>(var[o]) + eps);
      for (std::int64_t py = 0; py < H; ++py)
        for (std::int64_t px = 0; px < W; ++px) {
          double sum = bias[o], magnitude = std::abs(bias[o]);
          for (std::int64_t i = 0; i < I; ++i)
            for (std::int64_t ky = 0; ky < 3; ++ky)
              for (std::int64_t kx = 0; kx < 3; ++kx) {
                const std::int64_t sy = py + ky - 1, sx = px + kx - 1;
                if (sy < 0 || sy >= H || sx < 0 || sx >= W) continue;
                const double term = static_cast<double>(w[((o * I + i) * 3 + ky) * 3 + kx]) *
                                    xf[((b * I + i) * H + sy) * W + sx];
                sum += term, magnitude += std::abs(term);
              }
          const double expected = std::max((sum - mean[o]) * s + beta[o], 0.0);
          const double tolerance = 1e-5 * (magnitude * s + std::abs(mean[o] * s) + std::abs(beta[o]));
          const size_t e = static_cast<size_t>(((b * O + o) * H + py) * W + px);
          EXPECT_NEAR(yf[e], expected, tolerance) << "f32 y at " << e;
          EXPECT_NEAR(value(y[e]), expected, tolerance + std::ldexp(std::abs(expected), -8)) << "bf16 y at " << e;
          EXPECT_EQ(y[e], bf16(yf[e])) << "bf16 y is the f32 y rounded, at " << e;
        }
    }
  // FP32 prepared weights run the 3 x 3 pad-1 convolutions only, on x and y of one dtype.
  EXPECT_THROW(backend->conv2d_prepared_forward(TensorRef{x.data(), {B, I, H, W}, DType::BF16}, prepared_ref,
                                                TensorRef{}, prepared_bias, weight, 1, true,
                                                TensorRef{yf.data(), {B, O, H, W}, DType::F32}),
               Error);
}

// Which arithmetic each convolution of a BF16 network gets (Backend::prepared_conv_dtype): on the
// AMX tiles (and AMD's AVX512_BF16) all BF16; on Intel's AVX512_BF16 alone the 3 x 3 pad-1 ones
// BF16 only where they double at most 128 input channels, the others FP32; the 1 x 1 and transposed ones BF16 (their FP32 kernels
// would need an FP32 copy of the BF16 input); fp16 and the CPU reference backend unchanged.
TEST(CpuBf16Network, TheRuleByKernelFamilyAndShape) {
  auto avx512 = make_cpu_backend_emulated_bf16(), amx = make_cpu_backend_emulated_bf16(/*amx=*/true);
  struct Case {
    Shape weight;
    int pad;
    bool transposed;
    DType on_avx512;
  };
  const Case cases[] = {{{128, 64, 3, 3}, 1, false, DType::BF16},   {{256, 128, 3, 3}, 1, false, DType::BF16},
                        {{512, 256, 3, 3}, 1, false, DType::F32},   {{128, 128, 3, 3}, 1, false, DType::F32},
                        {{255, 128, 3, 3}, 1, false, DType::F32},   {{64, 64, 3, 3}, 1, false, DType::F32},
                        {{64, 128, 3, 3}, 1, false, DType::F32},    {{512, 1024, 3, 3}, 1, false, DType::F32},
                        {{8, 4, 3, 3}, 1, false, DType::BF16},      {{8, 4, 3, 3}, 0, false, DType::BF16},
                        {{12, 64, 1, 1}, 0, false, DType::BF16},    {{512, 256, 2, 2}, 0, true, DType::BF16}};
  for (const Case& c : cases) {
    SCOPED_TRACE(shape_str(c.weight) + " pad " + std::to_string(c.pad) + (c.transposed ? " transposed" : ""));
    EXPECT_EQ(avx512->prepared_conv_dtype(c.weight, c.pad, c.transposed, DType::BF16), c.on_avx512);
    EXPECT_EQ(amx->prepared_conv_dtype(c.weight, c.pad, c.transposed, DType::BF16), DType::BF16);
    EXPECT_EQ(avx512->prepared_conv_dtype(c.weight, c.pad, c.transposed, DType::F16), DType::F16);
    EXPECT_EQ(make_cpu_reference_backend()->prepared_conv_dtype(c.weight, c.pad, c.transposed, DType::BF16),
              DType::BF16);
    EXPECT_TRUE(cpu::bf16_winograd_pays(Bf16Kernels::Avx512, /*dot_outpaces_fma=*/true, c.weight));
  }
  // The tiny network (a U-Net of depth 2 on width 4: down1 4 -> 8, down2 8 -> 8 bilinear or
  // 8 -> 16 transposed): its BF16 convolutions by name, the other 3 x 3 ones FP32, and the
  // activations around each still BF16.
  for (const bool transposed : {false, true}) {
    SCOPED_TRACE(transposed ? "transposed" : "bilinear");
    const ModelConfig c = test::tiny_config(OccupancyInput::None, transposed);
    const test::TinyData d = test::tiny_data(c, 1, 5, 0.4);
    for (Backend* be : {avx512.get(), amx.get()}) {
      PillarSegNet net(c, *be, 3);
      net.set_precision(Precision::BF16);
      net.forward(d.batch, false);
      std::vector<std::string> fp32, bf16_convs;
      for (const GraphNode& n : net.graph(false).nodes()) {
        if (n.op != OpKind::PreparedConv2d && n.op != OpKind::PreparedConvTranspose2d) continue;
        const auto a = n.as<PreparedConv2dArgs>();
        (net.graph(false).at(a.prepared).dtype == DType::F32 ? fp32 : bf16_convs).push_back(n.name);
        EXPECT_EQ(net.graph(false).at(a.x).dtype, DType::BF16) << n.name;
        EXPECT_EQ(net.graph(false).at(a.y).dtype, n.name == "head" ? DType::F32 : DType::BF16) << n.name;
      }
      if (be == amx.get()) {
        EXPECT_TRUE(fp32.empty()) << fmt::format("{}", fmt::join(fp32, " "));
        continue;
      }
      const std::vector<std::string> expected_bf16 =
          transposed ? std::vector<std::string>{"down1.conv1", "down2.conv1", "up1.up", "up2.up", "head"}
                     : std::vector<std::string>{"down1.conv1", "head"};
      EXPECT_EQ(bf16_convs, expected_bf16);
      EXPECT_EQ(fp32.size(), transposed ? 6u : 7u) << fmt::format("{}", fmt::join(fp32, " "));
    }
  }
}

// ---- the whole model ----

// A few training steps (BatchNorm statistics and weights away from their initial values), then
// the evaluation forward in FP32 and in BF16 on the CPU (the model of the AMX tiles, where every
// convolution runs BF16; the model of AVX512_BF16, where the rule of prepared_conv_dtype runs
// some of them FP32; and the instructions where present), and in BF16 on the CUDA backend
// (emulation): the CPU's 3 x 3 convolutions are Winograd F(2x2, 3x3), the CUDA backend's direct.
// With the occupancy stream the canvas is FP32 and rounded whole; with pillars alone they are
// scattered straight into the 16-bit canvas (the third variant).
TEST(CpuBf16Model, TracksFp32AndTheCudaBackend) {
  const std::pair<OccupancyInput, bool> variants[] = {{OccupancyInput::Occupancy3D, false},
                                                      {OccupancyInput::Occupancy3D, true},
                                                      {OccupancyInput::None, false}};
  for (const auto& [occupancy, transposed] : variants) {
    const std::string variant = std::string(transposed ? "transposed" : "bilinear") +
                                (occupancy == OccupancyInput::None ? "_pillars_alone" : "");
    SCOPED_TRACE(variant);
    const ModelConfig c = test::tiny_config(occupancy, transposed);
    const test::TinyData d = test::tiny_data(c, 2, 23, 0.4);
    auto emulated = make_cpu_backend_emulated_bf16(/*amx=*/true);
    PillarSegNet net(c, *emulated, 3);
    for (int64_t step = 1; step <= 3; ++step) {
      net.parameters().zero_grads();
      net.forward(d.batch, true);
      net.loss(d.labels, LossKind::CrossEntropy, test::kCoefficients);
      net.backward();
      AdamOptions adam;
      adam.lr = 1e-2;
      Ref values = net.parameters().values(), m = net.parameters().adam_m(),
          v = net.parameters().adam_v();
      emulated->adam_step(values, net.parameters().grads(), m, v, step, adam);
    }
    net.forward(d.batch, false);
    const Tensor<float> fp32 = net.download_logits();
    const Tensor<uint8_t> labels32 = net.predict_labels();
    net.set_precision(Precision::BF16);
    net.set_op_timing(true);
    net.forward(d.batch, false);
    const Tensor<float> bf16_cpu = net.download_logits();
    const Tensor<uint8_t> labels16 = net.predict_labels();
    // Again: the weights (w16 and the Winograd-transformed U) as prepared the first time.
    const int64_t preparations = net.op_times().at("prepared weights bf16").calls;
    net.forward(d.batch, false);
    net.set_op_timing(false);
    EXPECT_EQ(net.op_times().at("prepared weights bf16").calls, preparations);
    EXPECT_EQ(net.download_logits(), bf16_cpu);
    const auto nmse = [](const Tensor<float>& a, const Tensor<float>& r) {
      double num = 0, den = 0;
      for (int64_t i = 0; i < r.numel(); ++i) {
        const double e = static_cast<double>(a.data()[i]) - r.data()[i];
        num += e * e, den += static_cast<double>(r.data()[i]) * r.data()[i];
      }
      return num / den;
    };
    const double against_fp32 = nmse(bf16_cpu, fp32);
    RecordProperty("nmse_" + variant, fmt::format("{:.3g}", against_fp32));
    EXPECT_LT(against_fp32, 1e-5);  // the CUDA backend's BF16 measures 2.4e-7 here
    EXPECT_GT(against_fp32, 0.0) << "BF16 must round something";
    int64_t same = 0;
    for (int64_t i = 0; i < labels32.numel(); ++i) same += labels32.data()[i] == labels16.data()[i];
    EXPECT_GE(static_cast<double>(same), 0.99 * static_cast<double>(labels32.numel()));

    // The CUDA backend's BF16 with the same parameters: the same prepared weights and roundings,
    // FP32 sums in another order.
    CudaBackend cuda_backend;
    PillarSegNet on_cuda(c, cuda_backend, 3);
    on_cuda.parameters().copy_values_from(net.parameters());
    on_cuda.set_precision(Precision::BF16);
    on_cuda.forward(d.batch, false);
    const double against_cuda = nmse(bf16_cpu, on_cuda.download_logits());
    RecordProperty("nmse_vs_cuda_" + variant, fmt::format("{:.3g}", against_cuda));
    // The CPU runs its 3 x 3 convolutions by Winograd F(2x2, 3x3), whose rounding of U and V
    // to BF16 adds about half again to the direct convolution's error (RMS; bf16_winograd.hpp):
    // within 2x its RMS, 4x its NMSE, of the CUDA backend's direct BF16 against FP32.
    const double cuda_against_fp32 = nmse(on_cuda.download_logits(), fp32);
    RecordProperty("nmse_cuda_" + variant, fmt::format("{:.3g}", cuda_against_fp32));
    EXPECT_LT(against_fp32, 4 * cuda_against_fp32);
    EXPECT_LT(against_cuda, 2 * (against_fp32 + cuda_against_fp32));

    const auto bf16_logits = [&](Backend& be) {
      PillarSegNet other(c, be, 3);
      other.parameters().copy_values_from(net.parameters());
      other.set_precision(Precision::BF16);
      other.forward(d.batch, false);
      return other.download_logits();
    };
    // AVX512_BF16 without AMX: the channel-doubling 3 x 3 convolutions (4 -> 8, and 8 -> 16 in
    // the transposed U-Net), the transposed ones and the head BF16, the other 3 x 3 ones FP32 on
    // the same BF16 activations: nearer FP32 than the all-BF16 network, and apart from it by
    // about the BF16 error.
    auto avx512_model = make_cpu_backend_emulated_bf16();
    const Tensor<float> mixed = bf16_logits(*avx512_model);
    const double mixed_against_fp32 = nmse(mixed, fp32), mixed_against_bf16 = nmse(mixed, bf16_cpu);
    RecordProperty("nmse_avx512_mixed_" + variant, fmt::format("{:.3g}", mixed_against_fp32));
    EXPECT_GT(mixed_against_fp32, 0.0) << "the BF16 layers and activations must round something";
    EXPECT_LT(mixed_against_fp32, against_fp32);
    EXPECT_GT(mixed_against_bf16, 0.0) << "the FP32 layers must change something";
    EXPECT_LT(mixed_against_bf16, 2 * (against_fp32 + mixed_against_fp32));
    if (cpu::avx512_bf16_available()) {  // the instructions
      auto native = make_cpu_backend();
      const Tensor<float> on_native = bf16_logits(*native);
      if (cpu::native_bf16_kernels() == Bf16Kernels::Amx || cpu::bf16_dot_outpaces_fma()) {
        // All BF16 (the tiles, or AMD's AVX512_BF16), near the tiles' model: the same roundings,
        // the Winograd products summed in another order, whose error (about K 2^-24 relative for K products, K <= 9 C here) is
        // a few percent at most of the BF16 rounding's (2^-9): within 1e-2 of its NMSE.
        EXPECT_LT(nmse(on_native, bf16_cpu), 1e-2 * against_fp32);
      } else {
        EXPECT_EQ(on_native, mixed);  // AVX-512 bit for bit its model, the same rule
      }
    }
    net.set_precision(Precision::F32);
    net.forward(d.batch, false);
    EXPECT_EQ(net.download_logits(), fp32) << "back to fp32 gives the fp32 logits bit for bit";
  }
}

}  // namespace
