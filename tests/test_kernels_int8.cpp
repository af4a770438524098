// The INT8 tensor-core pieces: mma.sync m16n8k32 .s8.s8 and .u8.s8 (kernels/mma.cuh) and the INT8
// convolutions (kernels/conv2d_mma_s8.cuh), on the emulation here and on a GPU as
// test_kernels_int8_gpu:
//   - m16n8k32 in one warp against the PTX ISA's fragment formulas: a hand-built case whose
//     product selects rows of B, and distinct values throughout, so that an element in the wrong
//     register or byte gives a wrong number; .u8.s8 by hand (A bytes 200 and 128 count +200 and
//     +128, and the .s8.s8 instruction on the same bytes -56 and -128) and on distinct values; on
//     the emulation also fragments laid out wrongly on purpose (two A registers swapped, A's bytes
//     reversed, B's K order strided), which must give other products, the wrap past 2^31 and the
//     count of 8,192 flops an instruction, for both;
//   - the weight preparation by hand (scales, ties to even, the clamp, an all-zero channel, the
//     BatchNorm fold, the padding to 32 channels per tap, the transposed layout) and against the
//     host's formulas on random weights;
//   - the convolutions (3x3 padded and not, 1x1, the transposed 2x2) against a host reference
//     that quantizes the same way and accumulates exactly in int64: with unit scales and no bias
//     y is the accumulator itself, exact; otherwise y equals the documented epilogue
//     fma(float(acc), sx sw, bias) bit for bit and lies within its roundings of the exact acc sx sw
//     + bias. Channels that are not multiples of 32, pixels that are not multiples of the tile,
//     batch 2, FP32 and BF16 in and out, ReLU on and off, split K (the same bits as unsplit),
//     reruns (the same bits), guard words around y, weights past I that must not matter (nothing of
//     x is read past I), and activations beyond 127 sx that clamp;
//   - non-negative activations (u8, mma .u8.s8) the same way: values between 127 sx and 255 sx
//     kept, negatives 0, beyond 255 sx clamped, the padding 0, the unsigned rounding rule by hand
//     and on values near half-integers, the transposed kind, split K, the instruction counts, and
//     S8x32 x with non_negative refused.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include "core/ops.hpp"
#include "core/rng.hpp"
#include "engine/cpu/int8_conv.hpp"
#include "kernels/common.cuh"
#include "kernels/conv2d_mma.cuh"
#include "kernels/conv2d_mma_s8.cuh"
#include "kernels/device_buffer.hpp"
#include "kernels/mma.cuh"
#include "tests/kernel_test_helpers.hpp"

using namespace pillarseg;
using cuda::DeviceBuffer;
using kernel_test::GuardedArray;

namespace {

// ---- mma.sync m16n8k32 s8 ----

// D = A (16 x 32) B (32 x 8) + C in int64, all row-major.
std::vector<std::int64_t> reference_product(const std::vector<std::int8_t>& a,
                                            const std::vector<std::int8_t>& b,
                                            const std::vector<std::int32_t>& c) {
  std::vector<std::int64_t> d(128);
  for (int row = 0; row < 16; ++row)
    for (int col = 0; col < 8; ++col) {
      std::int64_t sum = c[static_cast<size_t>(row * 8 + col)];
      for (int k = 0; k < 32; ++k)
        sum += std::int64_t{a[static_cast<size_t>(row * 32 + k)]} *
               b[static_cast<size_t>(k * 8 + col)];
      d[static_cast<size_t>(row * 8 + col)] = sum;
    }
  return d;
}

std::vector<std::int32_t> run_probe(const std::vector<std::int8_t>& a,
                                    const std::vector<std::int8_t>& b,
                                    const std::vector<std::int32_t>& c) {
  auto da = DeviceBuffer<std::int8_t>::from_host(a), db = DeviceBuffer<std::int8_t>::from_host(b);
  auto dc = DeviceBuffer<std::int32_t>::from_host(c);
  DeviceBuffer<std::int32_t> dd(128);
  cuda::mma_s8_fragment_probe(da.data(), db.data(), dc.data(), dd.data(), nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  return dd.to_host();
}

// D = A B + C with A's bytes unsigned (0..255), in int64.
std::vector<std::int64_t> reference_product_u8(const std::vector<std::uint8_t>& a,
                                               const std::vector<std::int8_t>& b,
                                               const std::vector<std::int32_t>& c) {
  std::vector<std::int64_t> d(128);
  for (int row = 0; row < 16; ++row)
    for (int col = 0; col < 8; ++col) {
      std::int64_t sum = c[static_cast<size_t>(row * 8 + col)];
      for (int k = 0; k < 32; ++k)
        sum += std::int64_t{a[static_cast<size_t>(row * 32 + k)]} *
               b[static_cast<size_t>(k * 8 + col)];
      d[static_cast<size_t>(row * 8 + col)] = sum;
    }
  return d;
}

std::vector<std::int32_t> run_probe_u8(const std::vector<std::uint8_t>& a,
                                       const std::vector<std::int8_t>& b,
                                       const std::vector<std::int32_t>& c) {
  auto da = DeviceBuffer<std::uint8_t>::from_host(a);
  auto db = DeviceBuffer<std::int8_t>::from_host(b);
  auto dc = DeviceBuffer<std::int32_t>::from_host(c);
  DeviceBuffer<std::int32_t> dd(128);
  cuda::mma_u8s8_fragment_probe(da.data(), db.data(), dc.data(), dd.data(), nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  return dd.to_host();
}

// A selects rows of B: A[r][k] = 1 where k = 2 r (rows 0-15 pick the even K rows) and -1 where
// k = 2 r + 1, so D[r][n] = B[2 r][n] - B[2 r + 1][n] + C[r][n], worked by hand below for B[k][n]
// = 3 k - n - 40 and C[r][n] = 1000 r + n: D[r][n] = -3 + 1000 r + n.
TEST(Int8Mma, HandBuiltCaseSelectsRowsOfB) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  std::vector<std::int8_t> a(512, 0), b(256);
  std::vector<std::int32_t> c(128);
  for (int r = 0; r < 16; ++r) {
    a[static_cast<size_t>(r * 32 + 2 * r)] = 1;
    a[static_cast<size_t>(r * 32 + 2 * r + 1)] = -1;
  }
  for (int k = 0; k < 32; ++k)
    for (int n = 0; n < 8; ++n)
      b[static_cast<size_t>(k * 8 + n)] = static_cast<std::int8_t>(3 * k - n - 40);
  for (int r = 0; r < 16; ++r)
    for (int n = 0; n < 8; ++n) c[static_cast<size_t>(r * 8 + n)] = 1000 * r + n;
  const std::vector<std::int32_t> d = run_probe(a, b, c);
  for (int r = 0; r < 16; ++r)
    for (int n = 0; n < 8; ++n)
      EXPECT_EQ(d[static_cast<size_t>(r * 8 + n)], -3 + 1000 * r + n)
          << "D[" << r << "][" << n << "]";
}

// Distinct values over the whole int8 range (-128 and 127 included): every element's place
// matters.
void distinct_operands(std::vector<std::int8_t>& a, std::vector<std::int8_t>& b,
                       std::vector<std::int32_t>& c) {
  a.resize(512), b.resize(256), c.resize(128);
  for (int i = 0; i < 512; ++i)
    a[static_cast<size_t>(i)] = static_cast<std::int8_t>((i * 97 + 13) % 256 - 128);
  for (int i = 0; i < 256; ++i)
    b[static_cast<size_t>(i)] = static_cast<std::int8_t>((i * 59 + 7) % 256 - 128);
  for (int i = 0; i < 128; ++i) c[static_cast<size_t>(i)] = (i % 11 - 5) * 100003;
  a[0] = -128, a[511] = 127, b[0] = -128, b[255] = 127;
}

// m16n8k32 .u8.s8: A[r][2 r] = 200 (bytes 0xC8) and A[r][2 r + 1] = 128 (0x80), so that D[r][n] =
// 200 B[2 r][n] + 128 B[2 r + 1][n] + C[r][n] = 328 (6 r - n - 40) + 128 x 3 + 1000 r + n, worked
// by hand for the B and C above. Read as signed the bytes are -56 and -128: the .s8.s8 instruction
// on the same registers gives -56 B[2 r][n] - 128 B[2 r + 1][n] + C[r][n], which must differ.
TEST(Int8Mma, U8HandBuiltCaseReadsBytesUnsigned) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  std::vector<std::uint8_t> a(512, 0);
  std::vector<std::int8_t> b(256);
  std::vector<std::int32_t> c(128);
  for (int r = 0; r < 16; ++r) {
    a[static_cast<size_t>(r * 32 + 2 * r)] = 200;
    a[static_cast<size_t>(r * 32 + 2 * r + 1)] = 128;
  }
  for (int k = 0; k < 32; ++k)
    for (int n = 0; n < 8; ++n)
      b[static_cast<size_t>(k * 8 + n)] = static_cast<std::int8_t>(3 * k - n - 40);
  for (int r = 0; r < 16; ++r)
    for (int n = 0; n < 8; ++n) c[static_cast<size_t>(r * 8 + n)] = 1000 * r + n;
  const std::vector<std::int32_t> d = run_probe_u8(a, b, c);
  std::vector<std::int8_t> a_signed(a.size());
  for (size_t i = 0; i < a.size(); ++i) a_signed[i] = static_cast<std::int8_t>(a[i]);
  const std::vector<std::int32_t> d_signed = run_probe(a_signed, b, c);
  for (int r = 0; r < 16; ++r)
    for (int n = 0; n < 8; ++n) {
      const int b0 = 6 * r - n - 40, b1 = b0 + 3, i = r * 8 + n;
      EXPECT_EQ(d[static_cast<size_t>(i)], 200 * b0 + 128 * b1 + 1000 * r + n)
          << "u8 D[" << r << "][" << n << "]";
      EXPECT_EQ(d_signed[static_cast<size_t>(i)], -56 * b0 - 128 * b1 + 1000 * r + n)
          << "s8 D[" << r << "][" << n << "]";
    }
}

TEST(Int8Mma, M16n8k32MatchesTheIsaLayout) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  std::vector<std::int8_t> a, b;
  std::vector<std::int32_t> c;
  distinct_operands(a, b, c);
  const std::vector<std::int32_t> d = run_probe(a, b, c);
  const std::vector<std::int64_t> expected = reference_product(a, b, c);
  for (size_t i = 0; i < 128; ++i)
    EXPECT_EQ(d[i], expected[i]) << "D[" << i / 8 << "][" << i % 8 << "]";
}

// .u8.s8 with distinct A bytes over 0..255 (0, 128 and 255 included): the same fragment layout as
// .s8.s8, A's bytes unsigned.
TEST(Int8Mma, M16n8k32U8S8MatchesTheIsaLayout) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  std::vector<std::int8_t> a_signed, b;
  std::vector<std::int32_t> c;
  distinct_operands(a_signed, b, c);
  std::vector<std::uint8_t> a(a_signed.size());
  for (size_t i = 0; i < a.size(); ++i) a[i] = static_cast<std::uint8_t>(a_signed[i]);
  a[0] = 255, a[1] = 128, a[511] = 0;
  const std::vector<std::int32_t> d = run_probe_u8(a, b, c);
  const std::vector<std::int64_t> expected = reference_product_u8(a, b, c);
  for (size_t i = 0; i < 128; ++i)
    EXPECT_EQ(d[i], expected[i]) << "D[" << i / 8 << "][" << i % 8 << "]";
}

#if defined(PILLARSEG_CUDA_EMULATION)
// Fragments built on purpose with a layout mistake, to show that the emulation's mma reads each
// register by the ISA's layout: a kernel that made one of these mistakes computes a wrong product
// here as it would on a GPU.
enum class Layout { Isa, SwapA1A2, ReversedABytes, StridedBK };

// Element i of lane (g, t)'s A fragment (register i / 4, byte i % 4): its row and column.
void a_place(Layout layout, int g, int t, int i, int& row, int& col) {
  int reg = i / 4, byte = i % 4;
  if (layout == Layout::SwapA1A2 && (reg == 1 || reg == 2)) reg = 3 - reg;
  if (layout == Layout::ReversedABytes) byte = 3 - byte;
  row = g + (reg % 2) * 8, col = 4 * t + byte + (reg / 2) * 16;
}
int b_row(Layout layout, int t, int i) {
  const int reg = i / 4, byte = i % 4;
  return layout == Layout::StridedBK ? t + 4 * byte + 16 * reg : 4 * t + byte + 16 * reg;
}

__global__ void layout_probe_kernel(const std::int8_t* a, const std::int8_t* b,
                                    const std::int32_t* c, Layout layout, std::int32_t* d) {
  const int lane = static_cast<int>(threadIdx.x), g = lane / 4, t = lane % 4;
  std::uint32_t ra[4] = {0, 0, 0, 0}, rb[2] = {0, 0};
  for (int i = 0; i < 16; ++i) {
    int row = 0, col = 0;
    a_place(layout, g, t, i, row, col);
    ra[i / 4] |= std::uint32_t{static_cast<std::uint8_t>(a[row * 32 + col])} << (8 * (i % 4));
  }
  for (int i = 0; i < 8; ++i)
    rb[i / 4] |= std::uint32_t{static_cast<std::uint8_t>(b[b_row(layout, t, i) * 8 + g])}
                 << (8 * (i % 4));
  std::int32_t rc[4], rd[4];
  for (int i = 0; i < 4; ++i) rc[i] = c[(g + (i >= 2 ? 8 : 0)) * 8 + 2 * t + (i & 1)];
  cuda::mma_m16n8k32_i8<cuda::Int8A::S8>(rd, ra, rb, rc);
  for (int i = 0; i < 4; ++i) d[(g + (i >= 2 ? 8 : 0)) * 8 + 2 * t + (i & 1)] = rd[i];
}

TEST(Int8Mma, WrongFragmentLayoutsGiveOtherProducts) {
  std::vector<std::int8_t> a, b;
  std::vector<std::int32_t> c;
  distinct_operands(a, b, c);
  const std::vector<std::int64_t> expected = reference_product(a, b, c);
  auto da = DeviceBuffer<std::int8_t>::from_host(a), db = DeviceBuffer<std::int8_t>::from_host(b);
  auto dc = DeviceBuffer<std::int32_t>::from_host(c);
  DeviceBuffer<std::int32_t> dd(128);
  for (const Layout layout :
       {Layout::Isa, Layout::SwapA1A2, Layout::ReversedABytes, Layout::StridedBK}) {
    cuda::launch_kernel(layout_probe_kernel, dim3(1), dim3(32), 0, nullptr, da.data(), db.data(),
                        dc.data(), layout, dd.data());
    PS_CUDA_CHECK(cudaDeviceSynchronize());
    const std::vector<std::int32_t> d = dd.to_host();
    int wrong = 0;
    for (size_t i = 0; i < 128; ++i) wrong += d[i] != expected[i] ? 1 : 0;
    if (layout == Layout::Isa)
      EXPECT_EQ(wrong, 0) << "the ISA's layout";
    else
      EXPECT_GE(wrong, 64) << "layout mistake " << static_cast<int>(layout) << " went unnoticed";
  }
}

// Without .satfinite the accumulation wraps modulo 2^32; one instruction counts 8,192 flops.
TEST(Int8Mma, WrapsPast2To31AndCountsItsFlops) {
  std::vector<std::int8_t> a(512, 1), b(256, 1);
  std::vector<std::int32_t> c(128, std::numeric_limits<std::int32_t>::max());
  const emu::InstructionCounts before = emu::instruction_counts();
  const std::vector<std::int32_t> d = run_probe(a, b, c);
  const emu::InstructionCounts after = emu::instruction_counts();
  for (size_t i = 0; i < 128; ++i) EXPECT_EQ(d[i], std::numeric_limits<std::int32_t>::min() + 31);
  EXPECT_EQ(after.mma_m16n8k32 - before.mma_m16n8k32, 1u);
  EXPECT_EQ(after.mma_m16n8k16, before.mma_m16n8k16);
  EXPECT_EQ(after.tensor_core_flops() - before.tensor_core_flops(), 2u * 16 * 8 * 32);

  // .u8.s8: 32 x 255 x 127 = 1,036,320 past the largest int32; one more instruction, as many flops.
  const std::vector<std::int32_t> du =
      run_probe_u8(std::vector<std::uint8_t>(512, 255), std::vector<std::int8_t>(256, 127), c);
  const emu::InstructionCounts after_u8 = emu::instruction_counts();
  for (size_t i = 0; i < 128; ++i)
    EXPECT_EQ(du[i], std::numeric_limits<std::int32_t>::min() + 1036320 - 1);
  EXPECT_EQ(after_u8.mma_m16n8k32 - after.mma_m16n8k32, 1u);
  EXPECT_EQ(after_u8.tensor_core_flops() - after.tensor_core_flops(), 2u * 16 * 8 * 32);
}
#endif

// ---- the weight preparation ----

struct PreparedS8 {
  std::vector<std::int8_t> w8;
  std::vector<float> scale, bias;
};

// The host's preparation, from the contract of conv2d_mma_s8.cuh: w' = w * bn scale (FP32),
// sw = max |w'| / 127, q = clamp(rint(w' / sw)); columns n = o (convolution, w (O, I, k, k)) or
// 4 o + s (transposed, w (I, O, 2, 2)).
PreparedS8 host_prepare(const std::vector<float>& w, const std::vector<float>& bias,
                        const std::vector<float>* bn,  // gamma, beta, mean, var (O each)
                        float eps, std::int64_t out_channels, std::int64_t in_channels, int taps,
                        bool transposed) {
  const std::int64_t columns = transposed ? 4 * out_channels : out_channels;
  const std::int64_t ip = op::half16_padded_channels(in_channels), kp = taps * ip;
  PreparedS8 p;
  p.w8.assign(static_cast<size_t>(columns * kp), 0);
  p.scale.resize(static_cast<size_t>(columns));
  p.bias.resize(static_cast<size_t>(columns));
  for (std::int64_t n = 0; n < columns; ++n) {
    const std::int64_t o = transposed ? n / 4 : n;
    const size_t oi = static_cast<size_t>(o);
    float scale = 1.0f, shift = 0.0f;
    if (bn != nullptr) {
      scale = bn[0][oi] / std::sqrt(bn[3][oi] + eps);
      shift = bn[1][oi] - scale * bn[2][oi];
    }
    const auto value = [&](std::int64_t column, std::int64_t c, int tap) {
      return transposed ? w[static_cast<size_t>((c * out_channels + column / 4) * 4 + column % 4)]
                        : w[static_cast<size_t>((column * in_channels + c) * taps + tap)] * scale;
    };
    float largest = 0.0f;
    for (std::int64_t c = 0; c < in_channels; ++c) {
      if (transposed) {
        for (std::int64_t s = 0; s < 4; ++s)
          largest = std::max(largest, std::abs(value(4 * o + s, c, 0)));
      } else {
        for (int tap = 0; tap < taps; ++tap)
          largest = std::max(largest, std::abs(value(n, c, tap)));
      }
    }
    const float sw = largest / 127.0f;
    p.scale[static_cast<size_t>(n)] = sw;
    p.bias[static_cast<size_t>(n)] = scale * (bias.empty() ? 0.0f : bias[oi]) + shift;
    for (int tap = 0; tap < taps; ++tap)
      for (std::int64_t c = 0; c < in_channels; ++c) {
        if (sw == 0.0f) continue;
        const float q = std::nearbyint(std::clamp(value(n, c, tap) / sw, -127.0f, 127.0f));
        p.w8[static_cast<size_t>(n * kp + tap * ip + c)] = static_cast<std::int8_t>(q);
      }
  }
  return p;
}

PreparedS8 device_prepare(const std::vector<float>& w, const std::vector<float>& bias,
                          const std::vector<float>* bn, float eps, const cuda::Conv2dShape& s,
                          bool transposed) {
  const std::int64_t columns = transposed ? 4 * s.out_channels : s.out_channels;
  const int taps = transposed ? 1 : static_cast<int>(s.kernel * s.kernel);
  auto dw = DeviceBuffer<float>::from_host(w);
  DeviceBuffer<float> dbias =
      bias.empty() ? DeviceBuffer<float>(1) : DeviceBuffer<float>::from_host(bias);
  std::vector<DeviceBuffer<float>> dbn;
  cuda::FoldedBatchNorm folded;
  if (bn != nullptr) {
    for (int i = 0; i < 4; ++i) dbn.push_back(DeviceBuffer<float>::from_host(bn[i]));
    folded = {dbn[0].data(), dbn[1].data(), dbn[2].data(), dbn[3].data(), eps};
  }
  DeviceBuffer<std::int8_t> w8(
      static_cast<size_t>(columns * op::half16_weight_k(s.in_channels, taps)));
  DeviceBuffer<float> scale(static_cast<size_t>(columns)), b_out(static_cast<size_t>(columns));
  const float* bias_pointer = bias.empty() ? nullptr : dbias.data();
  if (transposed)
    cuda::prepare_conv_transpose_weights_s8(dw.data(), bias_pointer, s.in_channels, s.out_channels,
                                            w8.data(), scale.data(), b_out.data(), nullptr);
  else
    cuda::prepare_conv_weights_s8(dw.data(), bias_pointer, folded, s, w8.data(), scale.data(),
                                  b_out.data(), nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  return {w8.to_host(), scale.to_host(), b_out.to_host()};
}

// O = 2, I = 3, 3x3 (Ip = 32, Kp = 9 x 32), eps 0. Channel 0 with a BatchNorm scale of 2 (gamma
// 1, var 0.25) and shift 0.25 - 2 x 0.5: its largest |w'| = 2 x 3.96875 = 7.9375 = 127 / 16, so
// sw = 1 / 16 and q = 16 w'; channel 1 (scale 1, shift 0.5) is all zero: sw = 0, q = 0.
TEST(Int8Weights, PreparedByHand) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  const cuda::Conv2dShape s{1, 3, 4, 4, 2, 3, 1};
  std::vector<float> w(2 * 3 * 9, 0.0f);
  const auto at = [&](int o, int c, int tap) -> float& {
    return w[static_cast<size_t>((o * 3 + c) * 9 + tap)];
  };
  at(0, 0, 0) = 3.96875f;    // w' 7.9375: q 127
  at(0, 1, 4) = -3.96875f;   // q -127
  at(0, 2, 8) = 0.015625f;   // w' 1 / 32 = sw / 2: q rint(0.5) = 0 (ties to even)
  at(0, 0, 5) = 0.046875f;   // w' 3 / 32 = 1.5 sw: q 2
  at(0, 1, 7) = -0.078125f;  // w' -5 / 32 = -2.5 sw: q -2
  at(0, 2, 1) = 0.5f;        // w' 1: q 16
  const std::vector<float> bn[4] = {{1.0f, 1.0f}, {0.25f, 0.5f}, {0.5f, 0.0f}, {0.25f, 1.0f}};
  const PreparedS8 p = device_prepare(w, {1.5f, -4.0f}, bn, 0.0f, s, false);
  ASSERT_EQ(p.w8.size(), 2u * 9 * 32);
  EXPECT_EQ(p.scale[0], 0.0625f);
  EXPECT_EQ(p.scale[1], 0.0f);
  EXPECT_EQ(p.bias[0], 2.0f * 1.5f + 0.25f - 2.0f * 0.5f);  // scale bias + beta - scale mean
  EXPECT_EQ(p.bias[1], -4.0f + 0.5f);
  std::vector<std::int8_t> expected(2 * 9 * 32, 0);  // row 0, column tap 32 + c
  expected[0 * 32 + 0] = 127;
  expected[4 * 32 + 1] = -127;
  expected[5 * 32 + 0] = 2;
  expected[7 * 32 + 1] = -2;
  expected[1 * 32 + 2] = 16;
  EXPECT_TRUE(kernel_test::same_bits(p.w8, expected));

  // The transposed kind, I = 2, O = 2, w (I, O, 2, 2): row 4 o + s, column c = q(w[c][o][s]);
  // output channel 0's largest |w| is 31.75 (sw 0.25), channel 1's 15.875 (sw 0.125), over both
  // input channels and the four sub-pixels, for each of its four rows.
  std::vector<float> wt(2 * 2 * 4, 0.0f);
  const auto wt_at = [&](int c, int o, int sub) -> float& {
    return wt[static_cast<size_t>((c * 2 + o) * 4 + sub)];
  };
  wt_at(0, 0, 2) = -31.75f;   // q -127
  wt_at(1, 0, 1) = 15.875f;   // 63.5 sw: q 64 (ties to even)
  wt_at(1, 1, 3) = 15.875f;   // q 127
  wt_at(0, 1, 0) = -7.9375f;  // -63.5 sw: q -64
  wt_at(0, 1, 1) = 0.1875f;   // 1.5 sw: q 2
  const PreparedS8 t =
      device_prepare(wt, {0.5f, -0.25f}, nullptr, 0.0f, {1, 2, 3, 3, 2, 2, 0}, true);
  ASSERT_EQ(t.w8.size(), 8u * 32);
  for (size_t sub = 0; sub < 4; ++sub) {
    EXPECT_EQ(t.scale[sub], 0.25f);
    EXPECT_EQ(t.scale[4 + sub], 0.125f);
    EXPECT_EQ(t.bias[sub], 0.5f);
    EXPECT_EQ(t.bias[4 + sub], -0.25f);
  }
  std::vector<std::int8_t> expected_t(8 * 32, 0);
  expected_t[2 * 32 + 0] = -127;
  expected_t[1 * 32 + 1] = 64;
  expected_t[(4 + 3) * 32 + 1] = 127;
  expected_t[(4 + 0) * 32 + 0] = -64;
  expected_t[(4 + 1) * 32 + 0] = 2;
  EXPECT_TRUE(kernel_test::same_bits(t.w8, expected_t));
}

// ---- the convolutions ----

// q of an activation by the contract: x (1 / sx) rounded to FP32, then to the nearest integer
// (ties to even), clamped to [-127, 127], or to [0, 255] for non-negative activations (u8); NaN 0.
std::int64_t quantize_activation(float x, float inverse_scale, bool non_negative = false) {
  const float product = x * inverse_scale;
  if (std::isnan(product)) return 0;
  const float low = non_negative ? 0.0f : -127.0f, high = non_negative ? 255.0f : 127.0f;
  return static_cast<std::int64_t>(std::nearbyint(std::clamp(product, low, high)));
}

float bf16_value(float x) {
  return cuda::bf16_bits_to_float(cuda::float_to_bf16_bits(x));
}

std::vector<std::uint16_t> bf16_bits(const std::vector<float>& v) {
  std::vector<std::uint16_t> bits(v.size());
  for (size_t i = 0; i < v.size(); ++i) bits[i] = cuda::float_to_bf16_bits(v[i]);
  return bits;
}

struct ConvCaseS8 {
  std::int64_t batch, in_channels, height, width, out_channels, kernel, pad;
  bool transposed, batchnorm, relu, x_bf16, y_bf16;
  // x's scale: max |x| / 127 divided by `clamp_factor` (> 1: values beyond 127 sx clamp).
  double clamp_factor = 1.0;
  // Integer x (|x| <= 127; non_negative: |x| <= 254), integer weights with max |w| 127 per
  // channel, sx 1, no bias: y = acc.
  bool unit_scales = false;
  // x quantized to u8 (ActivationsS8::non_negative), sx = max |x| / 255 / clamp_factor: x's
  // negative half quantizes to 0, and the values between 127 sx and 255 sx, which the signed mode
  // clamps, keep their value. No S8x32 x (refused).
  bool non_negative = false;
};

std::vector<float> uniform(size_t n, Rng& rng, double lo, double hi) {
  std::vector<float> v(n);
  for (float& x : v) x = static_cast<float>(rng.uniform(lo, hi));
  return v;
}

void check_conv_s8(const ConvCaseS8& cc) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  const cuda::Conv2dShape s{cc.batch,
                            cc.in_channels,
                            cc.height,
                            cc.width,
                            cc.out_channels,
                            cc.transposed ? 1 : cc.kernel,
                            cc.transposed ? 0 : cc.pad};
  const std::int64_t ho = cc.transposed ? 2 * s.height : s.out_height(),
                     wo = cc.transposed ? 2 * s.width : s.out_width();
  const int taps = static_cast<int>(s.kernel * s.kernel);
  const std::int64_t weights = s.out_channels * s.in_channels * (cc.transposed ? 4 : taps);
  Rng rng(29 + static_cast<std::uint64_t>(s.out_channels * 7 + s.in_channels));
  std::vector<float> x =
      uniform(static_cast<size_t>(s.batch * s.in_channels * s.height * s.width), rng, -2, 2);
  std::vector<float> w = uniform(static_cast<size_t>(weights), rng, -0.5, 0.5);
  std::vector<float> bias = uniform(static_cast<size_t>(s.out_channels), rng, -1, 1);
  if (cc.unit_scales) {
    for (float& v : x) v = std::round(v * (cc.non_negative ? 127.0f : 63.0f));
    for (float& v : w) v = std::round(v * 250.0f);     // within +-125 ...
    for (std::int64_t o = 0; o < s.out_channels; ++o)  // ... and 127 once per output channel
      w[static_cast<size_t>(cc.transposed ? o * 4 : o * s.in_channels * taps)] =
          o % 2 ? -127.0f : 127.0f;
    bias.clear();
  }
  if (cc.x_bf16)
    for (float& v : x) v = bf16_value(v);  // the values the kernel sees
  std::vector<float> bn[4];
  if (cc.batchnorm) {
    bn[0] = uniform(bias.size(), rng, 0.5, 1.5), bn[1] = uniform(bias.size(), rng, -0.5, 0.5);
    bn[2] = uniform(bias.size(), rng, -0.3, 0.3), bn[3] = uniform(bias.size(), rng, 0.5, 2);
  }
  float largest = 0.0f;
  for (float v : x) largest = std::max(largest, std::abs(v));
  const double levels = cc.non_negative ? 255.0 : 127.0;
  const float sx = cc.unit_scales ? 1.0f : static_cast<float>(largest / levels / cc.clamp_factor);
  const float inverse = 1.0f / sx;

  // The preparation, on the device and on the host.
  const PreparedS8 p =
      device_prepare(w, bias, cc.batchnorm ? bn : nullptr, 1e-5f, s, cc.transposed);
  const PreparedS8 host = host_prepare(w, bias, cc.batchnorm ? bn : nullptr, 1e-5f, s.out_channels,
                                       s.in_channels, cc.transposed ? 1 : taps, cc.transposed);
  ASSERT_TRUE(kernel_test::same_bits(p.w8, host.w8));
  ASSERT_TRUE(kernel_test::same_bits(p.scale, host.scale));
  // The folded bias within a rounding or two (a GPU may fuse its multiply and add).
  for (size_t n = 0; n < p.bias.size(); ++n)
    ASSERT_NEAR(p.bias[n], host.bias[n], 1e-6 * (1 + std::abs(host.bias[n]))) << "bias " << n;
  if (cc.unit_scales) {
    for (float v : p.scale) ASSERT_EQ(v, 1.0f);
  }

  // The reference: exact int64 accumulators, then the epilogue.
  const std::int64_t ip = op::half16_padded_channels(s.in_channels),
                     kp = (cc.transposed ? 1 : taps) * ip;
  std::vector<std::int64_t> qx(x.size());
  std::int64_t clamped = 0, beyond_127 = 0, negative = 0;
  for (size_t i = 0; i < x.size(); ++i) {
    qx[i] = quantize_activation(x[i], inverse, cc.non_negative);
    const double scaled = static_cast<double>(x[i]) * inverse;
    clamped += std::abs(scaled) > levels + 0.5 ? 1 : 0;
    beyond_127 += scaled > 127.5 ? 1 : 0;
    negative += scaled < -0.5 ? 1 : 0;
  }
  if (cc.clamp_factor > 1.0) {
    EXPECT_GT(clamped, static_cast<std::int64_t>(x.size() / 10)) << "the case should clamp";
  } else {
    EXPECT_EQ(clamped, 0);
  }
  if (cc.non_negative) {  // what the signed mode would clamp, and negatives that become 0
    EXPECT_GT(beyond_127, static_cast<std::int64_t>(x.size() / 10));
    EXPECT_GT(negative, static_cast<std::int64_t>(x.size() / 10));
  }
  const std::int64_t out_count = s.batch * s.out_channels * ho * wo;
  std::vector<std::int64_t> acc(static_cast<size_t>(out_count), 0);
  for (std::int64_t b = 0; b < s.batch; ++b)
    for (std::int64_t o = 0; o < s.out_channels; ++o)
      for (std::int64_t oy = 0; oy < ho; ++oy)
        for (std::int64_t ox = 0; ox < wo; ++ox) {
          std::int64_t sum = 0;
          for (std::int64_t c = 0; c < s.in_channels; ++c) {
            if (cc.transposed) {
              const std::int64_t n = 4 * o + (oy % 2) * 2 + ox % 2;
              sum += std::int64_t{p.w8[static_cast<size_t>(n * kp + c)]} *
                     qx[static_cast<size_t>(
                         ((b * s.in_channels + c) * s.height + oy / 2) * s.width + ox / 2)];
              continue;
            }
            for (int tap = 0; tap < taps; ++tap) {
              const std::int64_t iy = oy + tap / s.kernel - s.pad, ix = ox + tap % s.kernel - s.pad;
              if (iy < 0 || iy >= s.height || ix < 0 || ix >= s.width) continue;
              sum +=
                  std::int64_t{p.w8[static_cast<size_t>(o * kp + tap * ip + c)]} *
                  qx[static_cast<size_t>(((b * s.in_channels + c) * s.height + iy) * s.width + ix)];
            }
          }
          acc[static_cast<size_t>(((b * s.out_channels + o) * ho + oy) * wo + ox)] = sum;
        }

  // The device: x as FP32 or BF16, y between guard words, unsplit and split, twice.
  using cuda::ActivationLayout;
  GuardedArray<float> dx_f(x);
  GuardedArray<std::uint16_t> dx_h(bf16_bits(x));
  auto dw8 = DeviceBuffer<std::int8_t>::from_host(p.w8);
  auto dscale = DeviceBuffer<float>::from_host(p.scale),
       dbias = DeviceBuffer<float>::from_host(p.bias);
  GuardedArray<float> dy_f(out_count, 1);
  GuardedArray<std::uint16_t> dy_h(out_count, 3);
  const std::int64_t workspace_count =
      cc.transposed ? cuda::conv_transpose2d_mma_s8_forward_workspace(
                          s.batch, s.in_channels, s.height, s.width, s.out_channels)
                    : cuda::conv2d_mma_s8_forward_workspace(s);
  DeviceBuffer<std::int32_t> workspace(
      static_cast<size_t>(std::max<std::int64_t>(workspace_count, 1)));
  const ActivationLayout x_layout = cc.x_bf16 ? ActivationLayout::BF16 : ActivationLayout::F32;
  const cuda::ActivationsS8 x_in{cc.x_bf16 ? static_cast<const void*>(dx_h.data()) : dx_f.data(),
                                 x_layout, sx, cc.non_negative};
  const auto convolve = [&](const cuda::ActivationsS8& xs, const cuda::OutputS8& ys, bool split) {
    std::int32_t* ws = split ? workspace.data() : nullptr;
    if (cc.transposed)
      cuda::conv_transpose2d_mma_s8_forward(xs, dw8.data(), dscale.data(), dbias.data(), s.batch,
                                             s.in_channels, s.height, s.width, s.out_channels,
                                             cc.relu, ys, nullptr, ws);
    else
      cuda::conv2d_mma_s8_forward(xs, dw8.data(), dscale.data(), dbias.data(), s, cc.relu, ys,
                                  nullptr, ws);
    PS_CUDA_CHECK(cudaDeviceSynchronize());
  };
  const auto run = [&](const cuda::ActivationsS8& xs, bool split) -> std::vector<float> {
    const cuda::OutputS8 ys{cc.y_bf16 ? static_cast<void*>(dy_h.data()) : dy_f.data(),
                            cc.y_bf16 ? ActivationLayout::BF16 : ActivationLayout::F32, 1.0f};
    convolve(xs, ys, split);
    EXPECT_TRUE(dy_f.guards_intact());
    EXPECT_TRUE(dy_h.guards_intact());
    if (!cc.y_bf16) return dy_f.download();
    std::vector<float> y;
    for (std::uint16_t bits : dy_h.download()) y.push_back(cuda::bf16_bits_to_float(bits));
    return y;
  };
  const std::vector<float> y = run(x_in, false);
  EXPECT_TRUE(kernel_test::same_bits(run(x_in, false), y)) << "a rerun";
  if (workspace_count > 0) {
    EXPECT_TRUE(kernel_test::same_bits(run(x_in, true), y)) << "split K";
  }
  if (ip > s.in_channels) {  // A is zero past I: weights there (not zero now) change nothing
    std::vector<std::int8_t> padded = p.w8;
    for (size_t i = 0; i < padded.size(); ++i)
      if (static_cast<std::int64_t>(i) % ip >= s.in_channels) padded[i] = 77;
    dw8.copy_from_host(padded);
    EXPECT_TRUE(kernel_test::same_bits(run(x_in, false), y)) << "weights past the input channels";
    dw8.copy_from_host(p.w8);
  }

  // x quantized beforehand (S8x32): the host's quantization in blocks of 32 channels, zeros past
  // I, and the convolution of it gives the same bits. Signed only: u8 x has no int8 layout.
  const std::int64_t plane = s.height * s.width, x_blocks = ip / 32;
  GuardedArray<std::int8_t> dq(
      cuda::activations_s8_bytes(s.batch, s.in_channels, s.height, s.width));
  ASSERT_EQ(dq.size(), s.batch * ip * plane);
  std::vector<cuda::ActivationsS8> inputs = {x_in};
  if (!cc.non_negative) {
    cuda::quantize_activations_s8(x_in.data, x_layout, sx, s.batch, s.in_channels, s.height,
                                  s.width, dq.data(), nullptr);
    PS_CUDA_CHECK(cudaDeviceSynchronize());
    std::vector<std::int8_t> q_expected(static_cast<size_t>(dq.size()), 0);
    for (std::int64_t b = 0; b < s.batch; ++b)
      for (std::int64_t c = 0; c < s.in_channels; ++c)
        for (std::int64_t pixel = 0; pixel < plane; ++pixel)
          q_expected[static_cast<size_t>(((b * x_blocks + c / 32) * plane + pixel) * 32 + c % 32)] =
              static_cast<std::int8_t>(
                  qx[static_cast<size_t>((b * s.in_channels + c) * plane + pixel)]);
    EXPECT_TRUE(kernel_test::same_bits(dq.download(), q_expected)) << "quantize_activations_s8";
    EXPECT_TRUE(dq.guards_intact());
    const cuda::ActivationsS8 q_in{dq.data(), ActivationLayout::S8x32, sx};
    EXPECT_TRUE(kernel_test::same_bits(run(q_in, false), y)) << "S8x32 x";
    if (workspace_count > 0) {
      EXPECT_TRUE(kernel_test::same_bits(run(q_in, true), y)) << "S8x32 x, split K";
    }
    inputs.push_back(q_in);
  }

  double worst = 0;  // |y - exact| in units of the epilogue's rounding bound
  std::vector<float> values(static_cast<size_t>(out_count));  // act(fma(...)) before rounding
  for (std::int64_t i = 0; i < out_count; ++i) {
    const std::int64_t n_of = (i / (ho * wo)) % s.out_channels;  // output channel
    const std::int64_t column =
        cc.transposed ? 4 * n_of + ((i / wo) % ho % 2) * 2 + (i % wo) % 2 : n_of;
    const float scale = sx * p.scale[static_cast<size_t>(column)];
    const float b = p.bias[static_cast<size_t>(column)];
    const std::int64_t a = acc[static_cast<size_t>(i)];
    const float got = y[static_cast<size_t>(i)];
    if (cc.unit_scales && !cc.relu && !cc.y_bf16) {
      ASSERT_EQ(static_cast<double>(got), static_cast<double>(a)) << "accumulator " << i;
    }
    // The documented epilogue, bit for bit.
    float expected = std::fma(static_cast<float>(a), scale, b);
    if (cc.relu) expected = std::max(expected, 0.0f);
    values[static_cast<size_t>(i)] = expected;
    if (cc.y_bf16) expected = bf16_value(expected);
    ASSERT_EQ(got, expected) << "y[" << i << "] from accumulator " << a;
    // Against the exact value: float(acc) and the FMA round once each, BF16 once more.
    double exact = static_cast<double>(a) * scale + b;
    if (cc.relu) exact = std::max(exact, 0.0);
    const double u = cc.y_bf16 ? 0x1p-8 : 0x1p-24;
    const double bound = std::abs(static_cast<double>(a) * scale) * 0x1p-24 * (1 + u) +
                         std::abs(exact) * u * 1.0001 + 1e-30;
    EXPECT_LE(std::abs(got - exact), bound) << "y[" << i << "]";
    worst = std::max(worst, std::abs(got - exact) / bound);
  }
  ::testing::Test::RecordProperty("worst_error_in_rounding_bounds", std::to_string(worst));

  // y quantized (S8x32) with sy = max |v| / 100: the host's quantization of the epilogue's
  // values, zeros in the padding channels (GuardedArray fills them with 0xA7 first), from FP32
  // or BF16 x and from S8x32 x, split or not.
  float largest_value = 0.0f;
  for (float v : values) largest_value = std::max(largest_value, std::abs(v));
  const float sy = largest_value > 0.0f ? largest_value / 100.0f : 1.0f;
  const std::int64_t op = op::half16_padded_channels(s.out_channels), y_plane = ho * wo;
  GuardedArray<std::int8_t> dyq(cuda::activations_s8_bytes(s.batch, s.out_channels, ho, wo));
  std::vector<std::int8_t> yq_expected(static_cast<size_t>(dyq.size()), 0);
  for (std::int64_t i = 0; i < out_count; ++i) {
    const std::int64_t pixel = i % y_plane, o = (i / y_plane) % s.out_channels,
                       b = i / (y_plane * s.out_channels);
    yq_expected[static_cast<size_t>(((b * (op / 32) + o / 32) * y_plane + pixel) * 32 + o % 32)] =
        static_cast<std::int8_t>(quantize_activation(values[static_cast<size_t>(i)], 1.0f / sy));
  }
  for (const bool split : {false, true}) {
    if (split && workspace_count == 0) continue;
    for (const cuda::ActivationsS8& xs : inputs) {
      convolve(xs, {dyq.data(), ActivationLayout::S8x32, sy}, split);
      EXPECT_TRUE(kernel_test::same_bits(dyq.download(), yq_expected))
          << "S8x32 y from " << (xs.layout == ActivationLayout::S8x32 ? "S8x32" : "FP32/BF16")
          << " x" << (split ? ", split K" : "");
      EXPECT_TRUE(dyq.guards_intact());
    }
  }
}

TEST(ConvMmaS8, AccumulatorsExactWithUnitScales) {
  check_conv_s8({2, 45, 7, 9, 70, 3, 1, false, false, false, false, false, 1.0, true});
}
TEST(ConvMmaS8, Conv3x3PaddedBatchNormReluF32) {
  check_conv_s8({2, 5, 9, 11, 70, 3, 1, false, true, true, false, false});
}
TEST(ConvMmaS8, Conv3x3PaddedBf16InF32Out) {
  check_conv_s8({1, 40, 7, 6, 33, 3, 1, false, false, false, true, false});
}
TEST(ConvMmaS8, Conv3x3PaddedF32InBf16OutRelu) {
  check_conv_s8({2, 19, 5, 13, 12, 3, 1, false, true, true, false, true});
}
TEST(ConvMmaS8, Conv3x3UnpaddedBf16InOut) {
  check_conv_s8({1, 3, 6, 9, 8, 3, 0, false, true, false, true, true});
}
TEST(ConvMmaS8, Conv1x1) {
  check_conv_s8({2, 40, 5, 13, 12, 1, 0, false, false, false, false, false});
}
// 96 channels (3 K steps a tap, 27 in all) on 20 pixels x 130 columns (two tiles of 128): K
// splits in 3 with the workspace; the integer sums give the same bits.
TEST(ConvMmaS8, ManyChannelsSplitKBf16) {
  EXPECT_EQ(cuda::conv2d_mma_s8_forward_workspace({1, 96, 4, 5, 130, 3, 1}), 3 * 20 * 130);
  EXPECT_EQ(cuda::conv2d_mma_s8_forward_workspace({1, 64, 400, 400, 64, 3, 1}), 0);
  check_conv_s8({1, 96, 4, 5, 130, 3, 1, false, true, true, true, true});
}
// sx = max |x| / (4 x 127): about three quarters of x lie beyond 127 sx and clamp to +-127.
TEST(ConvMmaS8, ActivationsBeyond127ScalesClamp) {
  check_conv_s8({2, 7, 6, 7, 9, 3, 1, false, false, false, false, false, 4.0});
}
TEST(ConvMmaS8, Transposed2x2) {
  check_conv_s8({2, 6, 3, 4, 5, 2, 0, true, false, false, false, false});
}
TEST(ConvMmaS8, Transposed2x2Bf16ReluUnitScales) {
  check_conv_s8({2, 37, 3, 5, 20, 2, 0, true, false, true, true, true, 1.0, true});
  check_conv_s8({1, 37, 3, 5, 20, 2, 0, true, false, false, false, false, 1.0, true});
}
// in_channels 512: 16 K steps for one tile of 24 pixels x 20 columns: 2 splits.
TEST(ConvMmaS8, Transposed2x2SplitK) {
  EXPECT_EQ(cuda::conv_transpose2d_mma_s8_forward_workspace(2, 512, 3, 4, 5), 2 * 24 * 20);
  check_conv_s8({2, 512, 3, 4, 5, 2, 0, true, false, true, false, true});
}

// Non-negative activations, quantized to u8 as staged and multiplied by mma.sync .u8.s8: the
// accumulators exact with x up to 254 (negatives 0), FP32 and BF16 x, the transposed kind, split K
// over a convolution and a transposed one (the same bits as unsplit), values beyond 255 sx that
// clamp.
TEST(ConvMmaS8, NonNegativeAccumulatorsExactWithUnitScales) {
  check_conv_s8({2, 45, 7, 9, 70, 3, 1, false, false, false, false, false, 1.0, true, true});
}
TEST(ConvMmaS8, NonNegativeConv3x3PaddedBf16InF32Out) {
  check_conv_s8({1, 40, 7, 6, 33, 3, 1, false, false, false, true, false, 1.0, false, true});
}
TEST(ConvMmaS8, NonNegativeConv3x3PaddedF32InBf16OutBatchNormRelu) {
  check_conv_s8({2, 19, 5, 13, 12, 3, 1, false, true, true, false, true, 1.0, false, true});
}
TEST(ConvMmaS8, NonNegativeTransposed2x2) {
  check_conv_s8({2, 6, 3, 4, 5, 2, 0, true, false, false, false, false, 1.0, false, true});
}
// 64 channels, 3x3: 18 K steps for one tile of 6 pixels x 8 columns, 2 splits; the transposed
// kind with 512 channels: 16 steps, 2 splits.
TEST(ConvMmaS8, NonNegativeSplitK) {
  EXPECT_EQ(cuda::conv2d_mma_s8_forward_workspace({1, 64, 2, 3, 8, 3, 1}), 2 * 6 * 8);
  check_conv_s8({1, 64, 2, 3, 8, 3, 1, false, false, true, true, false, 1.0, false, true});
  check_conv_s8({2, 512, 3, 4, 5, 2, 0, true, false, true, false, true, 1.0, false, true});
}
TEST(ConvMmaS8, NonNegativeActivationsBeyond255ScalesClamp) {
  check_conv_s8({2, 7, 6, 7, 9, 3, 1, false, false, false, false, false, 4.0, false, true});
}

// By hand, 1x1 with one channel of weight 127 (sw 1) and sx 1, so y = 127 q: the unsigned rule
// q = clamp(rint(x), 0, 255), ties to even, NaN and negatives 0, +inf 255; the signed mode
// clamps the same x at 127.
TEST(ConvMmaS8, NonNegativeQuantizesByHand) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  const float inf = std::numeric_limits<float>::infinity();
  const std::vector<float> x = {std::numeric_limits<float>::quiet_NaN(),
                                inf,
                                -inf,
                                -0.0f,
                                -3.5f,
                                0.49f,
                                2.5f,
                                127.5f,
                                128.5f,
                                200.0f,
                                254.5f,
                                255.4f,
                                255.6f,
                                1e30f};
  const float q_u8[] = {0, 255, 0, 0, 0, 0, 2, 128, 128, 200, 254, 255, 255, 255};
  const float q_s8[] = {0, 127, -127, 0, -4, 0, 2, 127, 127, 127, 127, 127, 127, 127};
  const auto n = static_cast<std::int64_t>(x.size());
  const cuda::Conv2dShape s{1, 1, 1, n, 1, 1, 0};
  const PreparedS8 p = device_prepare({127.0f}, {}, nullptr, 0.0f, s, false);
  ASSERT_EQ(p.scale[0], 1.0f);
  auto dx = DeviceBuffer<float>::from_host(x);
  auto dw8 = DeviceBuffer<std::int8_t>::from_host(p.w8);
  auto dscale = DeviceBuffer<float>::from_host(p.scale),
       dbias = DeviceBuffer<float>::from_host(p.bias);
  DeviceBuffer<float> dy(x.size());
  for (const bool non_negative : {true, false}) {
    cuda::conv2d_mma_s8_forward({dx.data(), cuda::ActivationLayout::F32, 1.0f, non_negative},
                                dw8.data(), dscale.data(), dbias.data(), s, false,
                                {dy.data(), cuda::ActivationLayout::F32, 1.0f}, nullptr);
    PS_CUDA_CHECK(cudaDeviceSynchronize());
    const std::vector<float> y = dy.to_host();
    for (size_t i = 0; i < x.size(); ++i)
      EXPECT_EQ(y[i], 127 * (non_negative ? q_u8[i] : q_s8[i]))
          << "x = " << x[i] << (non_negative ? ", u8" : ", s8");
  }
}

// Padding contributes 0 in the unsigned mode too: a 3 x 3 image of 200 (beyond 127 sx, sx 1)
// convolved with a 3x3 kernel of 127 (sw 1), pad 1, gives 200 x 127 times the taps inside: 4 at
// the corners, 6 on the edges, 9 in the middle.
TEST(ConvMmaS8, NonNegativePaddingContributesZero) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  const cuda::Conv2dShape s{1, 1, 3, 3, 1, 3, 1};
  const PreparedS8 p = device_prepare(std::vector<float>(9, 127.0f), {}, nullptr, 0.0f, s, false);
  ASSERT_EQ(p.scale[0], 1.0f);
  auto dx = DeviceBuffer<float>::from_host(std::vector<float>(9, 200.0f));
  auto dw8 = DeviceBuffer<std::int8_t>::from_host(p.w8);
  auto dscale = DeviceBuffer<float>::from_host(p.scale),
       dbias = DeviceBuffer<float>::from_host(p.bias);
  DeviceBuffer<float> dy(9);
  cuda::conv2d_mma_s8_forward({dx.data(), cuda::ActivationLayout::F32, 1.0f, true}, dw8.data(),
                              dscale.data(), dbias.data(), s, false,
                              {dy.data(), cuda::ActivationLayout::F32, 1.0f}, nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  const std::vector<float> y = dy.to_host();
  const int taps[9] = {4, 6, 4, 6, 9, 6, 4, 6, 4};
  for (size_t i = 0; i < 9; ++i)
    EXPECT_EQ(y[i], static_cast<float>(200 * 127 * taps[i]))
        << "y[" << i / 3 << "][" << i % 3 << "]";
}

// The unsigned rule rounds the FP32 product x r too (values whose exact product lies just past a
// half-integer but rounds onto it go to the even integer), over the whole u8 range, and agrees
// with the host's rule on values over several orders of magnitude: through a 1x1 convolution of
// one channel with weight 127 (sw 1), y = fma(127 q, sx, 0).
TEST(ConvMmaS8, NonNegativeQuantizationRoundsTheFp32ProductFirst) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  const float sx = 0.3f, r = 1.0f / sx;
  std::vector<float> x;
  std::vector<std::int64_t> expected;
  for (int k = 0; k < 255; ++k) {  // as in QuantizationRoundsTheFp32ProductFirst
    const float target = static_cast<float>(k) + 0.5f;
    float v = target / r;
    for (int i = 0; i < 32; ++i) v = std::nextafter(v, -2 * v);
    for (int i = 0; i < 64; ++i, v = std::nextafter(v, 2 * v)) {
      if (v * r == target && static_cast<double>(v) * r > target) {
        x.push_back(v);
        expected.push_back(static_cast<std::int64_t>(std::nearbyint(target)));
        break;
      }
    }
  }
  ASSERT_GE(x.size(), 40u) << "too few such values found";
  Rng rng(43);
  for (int i = 0; i < 500; ++i) {
    x.push_back(static_cast<float>(rng.normal() * std::pow(10.0, rng.uniform(-2.0, 2.5))));
    expected.push_back(quantize_activation(x.back(), r, true));
  }
  const auto n = static_cast<std::int64_t>(x.size());
  const cuda::Conv2dShape s{1, 1, 1, n, 1, 1, 0};
  const PreparedS8 p = device_prepare({127.0f}, {}, nullptr, 0.0f, s, false);
  auto dx = DeviceBuffer<float>::from_host(x);
  auto dw8 = DeviceBuffer<std::int8_t>::from_host(p.w8);
  auto dscale = DeviceBuffer<float>::from_host(p.scale),
       dbias = DeviceBuffer<float>::from_host(p.bias);
  DeviceBuffer<float> dy(x.size());
  cuda::conv2d_mma_s8_forward({dx.data(), cuda::ActivationLayout::F32, sx, true}, dw8.data(),
                              dscale.data(), dbias.data(), s, false,
                              {dy.data(), cuda::ActivationLayout::F32, 1.0f}, nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  const std::vector<float> y = dy.to_host();
  for (size_t i = 0; i < x.size(); ++i)
    ASSERT_EQ(y[i], std::fma(static_cast<float>(127 * expected[i]), sx, 0.0f))
        << "x = " << x[i] << ", x r = " << x[i] * r << ", q " << expected[i];
}

// The product x r is rounded to FP32 before it is rounded to an integer: values whose exact
// product lies just past a half-integer but rounds onto it in FP32 go to the even integer (a fused
// multiply-add would round them away from it). Found by search for r = 1 / 0.3.
TEST(ConvMmaS8, QuantizationRoundsTheFp32ProductFirst) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  const float sx = 0.3f, r = 1.0f / sx;
  std::vector<float> x;
  std::vector<std::int8_t> expected;
  for (int k = -127; k < 127; ++k) {  // the half-integers k + 0.5 and the values near k + 0.5 sx
    const float target = static_cast<float>(k) + 0.5f;
    float v = target / r;
    for (int i = 0; i < 32; ++i) v = std::nextafter(v, -2 * v);  // 32 ulps towards zero
    for (int i = 0; i < 64; ++i, v = std::nextafter(v, 2 * v)) {
      if (v * r == target && std::abs(static_cast<double>(v) * r) > std::abs(target)) {
        x.push_back(v);
        expected.push_back(static_cast<std::int8_t>(std::nearbyint(target)));  // the even one
        break;
      }
    }
  }
  ASSERT_GE(x.size(), 20u) << "too few such values found";
  const auto n = static_cast<std::int64_t>(x.size());
  auto dx = DeviceBuffer<float>::from_host(x);
  DeviceBuffer<std::int8_t> q(static_cast<size_t>(cuda::activations_s8_bytes(1, 1, 1, n)));
  cuda::quantize_activations_s8(dx.data(), cuda::ActivationLayout::F32, sx, 1, 1, 1, n, q.data(),
                                nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  const std::vector<std::int8_t> got = q.to_host();
  for (size_t i = 0; i < x.size(); ++i) {
    EXPECT_EQ(got[32 * i], expected[i]) << "x = " << x[i] << ", x r = " << x[i] * r;
  }
}

// The CPU backend's INT8 rule (engine/cpu/int8_conv.hpp, quantize_int8 and int8_weight_scale)
// gives the same bytes, so that the two backends' INT8 convolutions agree bit for bit: values
// over several orders of magnitude, half-integer multiples of sx, both signs, infinities, NaN.
TEST(ConvMmaS8, QuantizationMatchesTheCpuBackend) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  const float sx = 0.0173f, r = 1.0f / sx;
  Rng rng(41);
  std::vector<float> x;
  for (int i = 0; i < 2000; ++i)
    x.push_back(static_cast<float>(rng.normal() * std::pow(10.0, rng.uniform(-3.0, 1.0))));
  for (int k = -130; k <= 130; ++k) x.push_back((static_cast<float>(k) + 0.5f) * sx);
  x.insert(x.end(),
           {std::numeric_limits<float>::infinity(), -std::numeric_limits<float>::infinity(),
            std::numeric_limits<float>::quiet_NaN(), 0.0f, -0.0f, 1e30f, -1e30f});
  const auto n = static_cast<std::int64_t>(x.size());
  auto dx = DeviceBuffer<float>::from_host(x);
  DeviceBuffer<std::int8_t> q(static_cast<size_t>(cuda::activations_s8_bytes(1, 1, 1, n)));
  cuda::quantize_activations_s8(dx.data(), cuda::ActivationLayout::F32, sx, 1, 1, 1, n, q.data(),
                                nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  const std::vector<std::int8_t> got = q.to_host();
  for (size_t i = 0; i < x.size(); ++i)
    ASSERT_EQ(got[32 * i], cpu::quantize_int8(x[i], r)) << "x = " << x[i];

  // Weights: the scale and the bytes of one output channel.
  const std::vector<float> w = {0.31f, -0.07f, 0.0f, 0.155f, -0.31f, 0.2f, 1e-6f, -0.0775f, 0.1f};
  const PreparedS8 p = device_prepare(w, {}, nullptr, 0.0f, {1, 1, 3, 3, 1, 3, 1}, false);
  const float sw = cpu::int8_weight_scale(0.31f);
  EXPECT_EQ(p.scale[0], sw);
  for (size_t tap = 0; tap < 9; ++tap) {
    const float expected = std::clamp(std::nearbyint(w[tap] / sw), -127.0f, 127.0f);
    EXPECT_EQ(p.w8[tap * 32], static_cast<std::int8_t>(expected)) << "tap " << tap;
  }
}

// A NaN quantizes to 0 and infinities clamp, the same on every device (and as on the CPU).
TEST(ConvMmaS8, NonFiniteActivationsQuantizeDeterministically) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  // 1x1, one input channel, one output channel of weight 127 (sw 1), sx 1: y = q(x) 127.
  const cuda::Conv2dShape s{1, 1, 1, 6, 1, 1, 0};
  const std::vector<float> x = {std::numeric_limits<float>::quiet_NaN(),
                                std::numeric_limits<float>::infinity(),
                                -std::numeric_limits<float>::infinity(),
                                2.5f,
                                -3.5f,
                                126.5f};
  const PreparedS8 p = device_prepare({127.0f}, {}, nullptr, 0.0f, s, false);
  ASSERT_EQ(p.scale[0], 1.0f);
  auto dx = DeviceBuffer<float>::from_host(x);
  auto dw8 = DeviceBuffer<std::int8_t>::from_host(p.w8);
  auto dscale = DeviceBuffer<float>::from_host(p.scale),
       dbias = DeviceBuffer<float>::from_host(p.bias);
  DeviceBuffer<float> dy(6);
  cuda::conv2d_mma_s8_forward({dx.data(), cuda::ActivationLayout::F32, 1.0f}, dw8.data(),
                              dscale.data(), dbias.data(), s, false,
                              {dy.data(), cuda::ActivationLayout::F32, 1.0f}, nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  const std::vector<float> y = dy.to_host();
  const float expected[6] = {0, 127 * 127, -127 * 127, 2 * 127, -4 * 127, 126 * 127};
  for (int i = 0; i < 6; ++i)
    EXPECT_EQ(y[static_cast<size_t>(i)], expected[i]) << "x = " << x[static_cast<size_t>(i)];
}

// Scales that are not positive and finite, and a misaligned S8x32 input, are refused with a
// message; an S8x32 input cannot be quantized again, nor be read as unsigned.
TEST(ConvMmaS8, RefusesBadScalesAndMisalignedInt8Tensors) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  using cuda::ActivationLayout;
  const cuda::Conv2dShape s{1, 1, 1, 1, 1, 1, 0};
  DeviceBuffer<float> x(1), scale(1), bias(1), y(1);
  DeviceBuffer<std::int8_t> w8(32), q(64);
  const auto convolve = [&](const cuda::ActivationsS8& xs, const cuda::OutputS8& ys) {
    return kernel_test::error_message([&] {
      cuda::conv2d_mma_s8_forward(xs, w8.data(), scale.data(), bias.data(), s, false, ys, nullptr);
    });
  };
  for (const float bad : {0.0f, -1.0f, std::numeric_limits<float>::infinity(),
                          std::numeric_limits<float>::quiet_NaN()}) {
    std::string message =
        convolve({x.data(), ActivationLayout::F32, bad}, {y.data(), ActivationLayout::F32, 1.0f});
    EXPECT_NE(message.find("activation scale must be positive and finite"), std::string::npos)
        << message;
    message =
        convolve({x.data(), ActivationLayout::F32, 1.0f}, {q.data(), ActivationLayout::S8x32, bad});
    EXPECT_NE(message.find("output scale must be positive and finite"), std::string::npos)
        << message;
  }
  std::string message = convolve({q.data() + 8, ActivationLayout::S8x32, 1.0f},
                                 {y.data(), ActivationLayout::F32, 1.0f});
  EXPECT_NE(message.find("S8x32 input must be 16-byte aligned"), std::string::npos) << message;
  message = kernel_test::error_message([&] {
    cuda::quantize_activations_s8(q.data(), ActivationLayout::S8x32, 1.0f, 1, 1, 1, 1, q.data(),
                                  nullptr);
  });
  EXPECT_NE(message.find("must be FP32 or BF16"), std::string::npos) << message;
  // S8x32 bytes are signed: non_negative (u8) needs FP32 or BF16 x.
  message = convolve({q.data(), ActivationLayout::S8x32, 1.0f, true},
                     {y.data(), ActivationLayout::F32, 1.0f});
  EXPECT_NE(message.find("non_negative needs an FP32 or BF16 input"), std::string::npos) << message;
}

#if defined(PILLARSEG_CUDA_EMULATION)
// What the emulation counts a convolution issue: every block of 128 pixels x BN columns runs Kp /
// 32 steps of 4 warps x (64 x BN / 2) / (16 x 8) mma.sync m16n8k32 (BN instructions, 8,192 flops
// each: 2 x 128 x BN x 32 a step), and copies its BN x 32 bytes of weights a step.
TEST(ConvMmaS8, EmulationCountsTheIssuedInstructions) {
  struct Case {
    cuda::Conv2dShape shape;
    std::int64_t blocks_m, blocks_n, bn, k_padded;
  };
  const Case cases[] = {
      {{2, 40, 5, 13, 12, 1, 0}, 2, 1, 64, 64},       // 130 pixels, 40 -> 64 channels
      {{1, 96, 4, 5, 130, 3, 1}, 1, 2, 128, 9 * 96},  // 130 columns in two tiles of 128
  };
  for (const Case& c : cases) {
    const cuda::Conv2dShape& s = c.shape;
    DeviceBuffer<float> x(static_cast<size_t>(s.batch * s.in_channels * s.height * s.width));
    DeviceBuffer<std::int8_t> w8(static_cast<size_t>(s.out_channels * c.k_padded));
    DeviceBuffer<float> scale(static_cast<size_t>(s.out_channels)), bias(scale.size());
    DeviceBuffer<float> y(
        static_cast<size_t>(s.batch * s.out_channels * s.out_height() * s.out_width()));
    PS_CUDA_CHECK(cudaMemset(x.data(), 0, x.size() * sizeof(float)));
    PS_CUDA_CHECK(cudaMemset(w8.data(), 0, w8.size()));
    PS_CUDA_CHECK(cudaMemset(scale.data(), 0, scale.size() * sizeof(float)));
    PS_CUDA_CHECK(cudaMemset(bias.data(), 0, bias.size() * sizeof(float)));
    for (const bool non_negative : {false, true}) {  // s8 x s8 and u8 x s8: the same counts
      const emu::InstructionCounts before = emu::instruction_counts();
      cuda::conv2d_mma_s8_forward({x.data(), cuda::ActivationLayout::F32, 1.0f, non_negative},
                                  w8.data(), scale.data(), bias.data(), s, false,
                                  {y.data(), cuda::ActivationLayout::F32, 1.0f}, nullptr);
      PS_CUDA_CHECK(cudaDeviceSynchronize());
      const emu::InstructionCounts after = emu::instruction_counts();
      const std::int64_t blocks = c.blocks_m * c.blocks_n, steps = c.k_padded / 32;
      EXPECT_EQ(static_cast<std::int64_t>(after.tensor_core_flops() - before.tensor_core_flops()),
                blocks * 2 * 128 * c.bn * c.k_padded);
      EXPECT_EQ(static_cast<std::int64_t>(after.mma_m16n8k32 - before.mma_m16n8k32),
                blocks * steps * c.bn);
      EXPECT_EQ(static_cast<std::int64_t>(after.cp_async_bytes - before.cp_async_bytes),
                blocks * steps * c.bn * 32);
    }
  }
}
#endif

}  // namespace
