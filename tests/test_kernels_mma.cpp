// The tensor-core pieces (kernels/mma.cuh) and the mixed-precision convolutions
// (kernels/conv2d_mma.cuh), on the emulation here and on a GPU as test_kernels_mma_gpu:
//   - BF16 and FP16 rounding to nearest even at hand-worked values: ties, the largest finite
//     value and overflow, FP16 subnormals, NaN;
//   - mma.sync m16n8k16 (both types) and ldmatrix (x2, x4, with and without .trans) in one warp
//     against the PTX ISA's fragment formulas, with integer-valued elements all distinct, so that
//     a register in the wrong place gives a wrong number;
//   - the 16-bit activation kernels (half_ops.cuh) against the FP32 kernels on the same rounded
//     values: max-pool, zero-padded concatenation and channel copies exactly, the upsampling
//     within one 16-bit rounding, and a convolution with 16-bit input and output against the
//     FP32-in/out one within one rounding of its output;
//   - the convolutions (3x3 with and without padding, 1x1, BatchNorm folded, ReLU, the transposed
//     2x2) against a double reference computed from the same 16-bit-rounded inputs and weights.
//     Tolerance per element: the products are exact, so only the FP32 sums round: |err| <=
//     K 2^-24 sum_k |w_k a_k| + 2^-24 |y|. Against the FP32 reference (unrounded values) each
//     product is off by at most (2 u + u^2) |w a| with u = 2^-8 (BF16) or 2^-11 (FP16).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include "core/ops.hpp"
#include "core/rng.hpp"
#include "kernels/common.cuh"
#include "kernels/conv2d_mma.cuh"
#include "kernels/device_buffer.hpp"
#include "kernels/elementwise.cuh"
#include "kernels/half_ops.cuh"
#include "kernels/maxpool2d.cuh"
#include "kernels/mma.cuh"
#include "kernels/pad_concat.cuh"
#include "kernels/upsample_bilinear.cuh"
#include "tests/kernel_test_helpers.hpp"

using namespace pillarseg;
using cuda::DeviceBuffer;
using cuda::Half16;
using kernel_test::GuardedArray;

namespace {

float bits_float(std::uint32_t u) {
  float x;
  std::memcpy(&x, &u, 4);
  return x;
}

TEST(Half16, RoundsToNearestEven) {
  // BF16 keeps 8 significant bits: 1 + 2^-8 is half-way between 1 and 1 + 2^-7 -> even (1).
  EXPECT_EQ(cuda::float_to_bf16_bits(1.0f), 0x3F80);
  EXPECT_EQ(cuda::float_to_bf16_bits(1.0f + 0x1p-8f), 0x3F80);
  EXPECT_EQ(cuda::float_to_bf16_bits(1.0f + 3 * 0x1p-8f), 0x3F82);  // half-way, odd below -> up
  EXPECT_EQ(cuda::float_to_bf16_bits(1.0f + 0x1p-8f + 0x1p-20f), 0x3F81);  // just above half-way
  EXPECT_EQ(cuda::float_to_bf16_bits(-2.5f), 0xC020);
  EXPECT_EQ(cuda::float_to_bf16_bits(bits_float(0x7F7FFFFFu)), 0x7F80);  // the largest float -> inf
  EXPECT_EQ(cuda::float_to_bf16_bits(bits_float(0x7F7F7FFFu)),
            0x7F7F);  // below half-way: stays finite
  const std::uint16_t nan = cuda::float_to_bf16_bits(std::numeric_limits<float>::quiet_NaN());
  EXPECT_TRUE(std::isnan(cuda::bf16_bits_to_float(nan)));
  EXPECT_TRUE(
      std::isnan(cuda::bf16_bits_to_float(cuda::float_to_bf16_bits(bits_float(0x7F800001u)))));
  EXPECT_EQ(cuda::bf16_bits_to_float(0x3F81), 1.0f + 0x1p-7f);

  // FP16: 11 significant bits, largest 65504, subnormals down to 2^-24.
  EXPECT_EQ(cuda::float_to_f16_bits(1.0f), 0x3C00);
  EXPECT_EQ(cuda::float_to_f16_bits(1.0f + 0x1p-11f), 0x3C00);
  EXPECT_EQ(cuda::float_to_f16_bits(1.0f + 3 * 0x1p-11f), 0x3C02);
  EXPECT_EQ(cuda::float_to_f16_bits(65504.0f), 0x7BFF);
  EXPECT_EQ(cuda::float_to_f16_bits(65519.0f), 0x7BFF);
  EXPECT_EQ(cuda::float_to_f16_bits(65520.0f), 0x7C00);  // half-way to 65536, odd below -> inf
  EXPECT_EQ(cuda::float_to_f16_bits(0x1p-24f), 0x0001);
  EXPECT_EQ(cuda::float_to_f16_bits(0x1p-25f), 0x0000);      // half-way to 2^-24 -> even 0
  EXPECT_EQ(cuda::float_to_f16_bits(3 * 0x1p-25f), 0x0002);  // 1.5 x 2^-24 -> even 2
  EXPECT_EQ(cuda::float_to_f16_bits(0x1p-14f), 0x0400);      // the smallest normal
  EXPECT_EQ(cuda::float_to_f16_bits(-0x1p-15f), 0x8200);     // a subnormal, negative
  EXPECT_EQ(cuda::f16_bits_to_float(0x0001), 0x1p-24f);
  EXPECT_EQ(cuda::f16_bits_to_float(0x7BFF), 65504.0f);
  EXPECT_EQ(cuda::f16_bits_to_float(0xC500), -5.0f);
  EXPECT_TRUE(std::isinf(cuda::f16_bits_to_float(0x7C00)));
  EXPECT_TRUE(std::isnan(
      cuda::f16_bits_to_float(cuda::float_to_f16_bits(std::numeric_limits<float>::quiet_NaN()))));
  // Every BF16 and FP16 value converts to float and back to itself (NaNs to a NaN).
  for (std::uint32_t b = 0; b < 65536; ++b) {
    const auto bits = static_cast<std::uint16_t>(b);
    const float x = cuda::bf16_bits_to_float(bits), h = cuda::f16_bits_to_float(bits);
    if (!std::isnan(x)) {
      EXPECT_EQ(cuda::float_to_bf16_bits(x), bits) << b;
    }
    if (!std::isnan(h)) {
      EXPECT_EQ(cuda::float_to_f16_bits(h), bits) << b;
    }
  }
}

template <Half16 H>
void check_mma() {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  // Distinct small integers: exact in both types, products and sums exact in float.
  std::vector<float> a(256), b(128), c(128);
  for (int i = 0; i < 256; ++i) a[static_cast<size_t>(i)] = static_cast<float>((i * 37) % 61 - 30);
  for (int i = 0; i < 128; ++i) b[static_cast<size_t>(i)] = static_cast<float>((i * 53) % 29 - 14);
  for (int i = 0; i < 128; ++i) c[static_cast<size_t>(i)] = static_cast<float>(i % 7 * 100);
  auto da = DeviceBuffer<float>::from_host(a), db = DeviceBuffer<float>::from_host(b),
       dc = DeviceBuffer<float>::from_host(c);
  DeviceBuffer<float> dd(128);
  cuda::mma_fragment_probe(da.data(), db.data(), dc.data(), H, dd.data(), nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  const std::vector<float> d = dd.to_host();
  for (int row = 0; row < 16; ++row) {
    for (int col = 0; col < 8; ++col) {
      double expected = c[static_cast<size_t>(row * 8 + col)];
      for (int k = 0; k < 16; ++k)
        expected += static_cast<double>(a[static_cast<size_t>(row * 16 + k)]) *
                    b[static_cast<size_t>(k * 8 + col)];
      EXPECT_EQ(d[static_cast<size_t>(row * 8 + col)], expected)
          << "D[" << row << "][" << col << "]";
    }
  }
}

TEST(Mma, M16n8k16Bf16MatchesTheIsaLayout) {
  check_mma<Half16::BF16>();
}
TEST(Mma, M16n8k16F16MatchesTheIsaLayout) {
  check_mma<Half16::F16>();
}

// ldmatrix_probe (conv2d_mma.cuh): x4, x4.trans, x2, x2.trans of v[r][c] = 256 r + c.
TEST(Mma, LdmatrixMatchesTheIsaLayout) {
  DeviceBuffer<std::uint32_t> out(32 * 12);
  cuda::ldmatrix_probe(out.data(), nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  const std::vector<std::uint32_t> got = out.to_host();
  const auto value = [](int row, int col) { return static_cast<std::uint32_t>(256 * row + col); };
  for (int lane = 0; lane < 32; ++lane) {
    const int g = lane / 4, t = lane % 4;
    for (int q = 0; q < 4; ++q) {
      const int r0 = (q % 2) * 8, c0 = (q / 2) * 8;  // matrix q's corner
      const std::uint32_t plain = value(r0 + g, c0 + 2 * t) | (value(r0 + g, c0 + 2 * t + 1) << 16);
      const std::uint32_t trans = value(r0 + 2 * t, c0 + g) | (value(r0 + 2 * t + 1, c0 + g) << 16);
      EXPECT_EQ(got[static_cast<size_t>(lane * 12 + q)], plain) << "x4 lane " << lane << " r" << q;
      EXPECT_EQ(got[static_cast<size_t>(lane * 12 + 4 + q)], trans)
          << "x4.trans lane " << lane << " r" << q;
      if (q < 2) {
        EXPECT_EQ(got[static_cast<size_t>(lane * 12 + 8 + q)], plain)
            << "x2 lane " << lane << " r" << q;
        EXPECT_EQ(got[static_cast<size_t>(lane * 12 + 10 + q)], trans)
            << "x2.trans lane " << lane << " r" << q;
      }
    }
  }
}

// cp_async_probe (conv2d_mma.cuh): each stage holds its source after its group's wait, stage 1
// zeros; on the emulation, the stages whose groups are still pending after wait<2> still hold
// what was there before (the copies land at the wait), and a misaligned copy is refused.
TEST(Mma, CpAsyncGroupsLandAtTheirWait) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  std::vector<std::uint32_t> source(3 * 32 * 4);
  for (size_t i = 0; i < source.size(); ++i) source[i] = static_cast<std::uint32_t>(0x1000 + 7 * i);
  auto d_source = DeviceBuffer<std::uint32_t>::from_host(source);
  DeviceBuffer<std::uint32_t> out(32 * 24);
  cuda::cp_async_probe(d_source.data(), out.data(), false, nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  const std::vector<std::uint32_t> got = out.to_host();
  for (int lane = 0; lane < 32; ++lane) {
    for (int s = 0; s < 3; ++s) {
      for (int w = 0; w < 4; ++w) {
        const std::uint32_t landed =
            s == 1 ? 0u : source[static_cast<size_t>((s * 32 + lane) * 4 + w)];
        const std::uint32_t after_first = got[static_cast<size_t>(lane * 24 + s * 4 + w)];
        if (s == 0) {
          EXPECT_EQ(after_first, landed) << "lane " << lane << " stage 0 after wait<2>";
        }
#if defined(PILLARSEG_CUDA_EMULATION)
        if (s > 0) {
          EXPECT_EQ(after_first, 0xDEADBEEFu)
              << "lane " << lane << " stage " << s << " before its wait";
        }
#endif
        EXPECT_EQ(got[static_cast<size_t>(lane * 24 + 12 + s * 4 + w)], landed)
            << "lane " << lane << " stage " << s << " after wait<0>";
      }
    }
  }
#if defined(PILLARSEG_CUDA_EMULATION)
  try {
    cuda::cp_async_probe(d_source.data(), out.data(), true, nullptr);
    PS_CUDA_CHECK(cudaDeviceSynchronize());
    ADD_FAILURE() << "a misaligned cp.async was not refused";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("16-byte aligned"), std::string::npos) << e.what();
  }
#endif
}

// ---- the convolutions ----

float round_half(float x, Half16 type) {
  return type == Half16::BF16 ? cuda::bf16_bits_to_float(cuda::float_to_bf16_bits(x))
                              : cuda::f16_bits_to_float(cuda::float_to_f16_bits(x));
}

std::vector<float> uniform(size_t n, Rng& rng, double lo, double hi) {
  std::vector<float> v(n);
  for (float& x : v) x = static_cast<float>(rng.uniform(lo, hi));
  return v;
}

struct ConvCase {
  std::int64_t batch, in_channels, height, width, out_channels, kernel, pad;
  bool batchnorm, relu;
};

void check_conv(const ConvCase& cc, Half16 type) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  const cuda::Conv2dShape s{cc.batch,        cc.in_channels, cc.height, cc.width,
                            cc.out_channels, cc.kernel,      cc.pad};
  const std::int64_t k = s.in_channels * s.kernel * s.kernel, ho = s.out_height(),
                     wo = s.out_width();
  Rng rng(11 + static_cast<uint64_t>(cc.out_channels));
  const std::vector<float> x =
      uniform(static_cast<size_t>(s.batch * s.in_channels * s.height * s.width), rng, -2, 2);
  const std::vector<float> w = uniform(static_cast<size_t>(s.out_channels * k), rng, -0.5, 0.5);
  const std::vector<float> bias = uniform(static_cast<size_t>(s.out_channels), rng, -1, 1);
  const std::vector<float> gamma = uniform(bias.size(), rng, 0.5, 1.5),
                           beta = uniform(bias.size(), rng, -0.5, 0.5),
                           mean = uniform(bias.size(), rng, -0.3, 0.3),
                           var = uniform(bias.size(), rng, 0.5, 2);
  auto dx = DeviceBuffer<float>::from_host(x), dw = DeviceBuffer<float>::from_host(w),
       dbias = DeviceBuffer<float>::from_host(bias), dg = DeviceBuffer<float>::from_host(gamma),
       dbeta = DeviceBuffer<float>::from_host(beta), dm = DeviceBuffer<float>::from_host(mean),
       dv = DeviceBuffer<float>::from_host(var);
  cuda::FoldedBatchNorm bn;
  if (cc.batchnorm) bn = {dg.data(), dbeta.data(), dm.data(), dv.data(), 1e-5f};
  DeviceBuffer<std::uint16_t> w16(static_cast<size_t>(
      s.out_channels * op::half16_weight_k(s.in_channels, s.kernel * s.kernel)));
  DeviceBuffer<float> b_out(static_cast<size_t>(s.out_channels));
  DeviceBuffer<float> dy(static_cast<size_t>(s.batch * s.out_channels * ho * wo));
  cuda::prepare_conv_weights(dw.data(), dbias.data(), bn, s, type, w16.data(), b_out.data(),
                             nullptr);
  // Unsplit, then with the workspace that lets a GEMM of few tiles split K (where it does).
  const std::int64_t workspace_floats = cuda::conv2d_mma_forward_workspace(s);
  DeviceBuffer<float> workspace(static_cast<size_t>(std::max<std::int64_t>(workspace_floats, 1)));
  for (const bool split : {false, true}) {
    SCOPED_TRACE(split ? "split K" : "unsplit");
    cuda::conv2d_mma_forward(dx.data(), false, w16.data(), b_out.data(), s, type, cc.relu,
                             dy.data(), false, nullptr, split ? workspace.data() : nullptr);
    PS_CUDA_CHECK(cudaDeviceSynchronize());
    const std::vector<float> y = dy.to_host();

    const double u = type == Half16::BF16 ? 0x1p-8 : 0x1p-11;
    double worst_vs_fp32 = 0;
    for (std::int64_t b = 0; b < s.batch; ++b) {
      for (std::int64_t o = 0; o < s.out_channels; ++o) {
        const size_t oi = static_cast<size_t>(o);
        float scale = 1.0f, shift = 0.0f;
        if (cc.batchnorm) {
          scale = gamma[oi] / std::sqrt(var[oi] + 1e-5f);
          shift = beta[oi] - scale * mean[oi];
        }
        for (std::int64_t oy = 0; oy < ho; ++oy) {
          for (std::int64_t ox = 0; ox < wo; ++ox) {
            double sum16 = 0, sum32 = 0, magnitude = 0;
            for (std::int64_t i = 0; i < s.in_channels; ++i) {
              for (std::int64_t ky = 0; ky < s.kernel; ++ky) {
                for (std::int64_t kx = 0; kx < s.kernel; ++kx) {
                  const std::int64_t iy = oy + ky - s.pad, ix = ox + kx - s.pad;
                  if (iy < 0 || iy >= s.height || ix < 0 || ix >= s.width) continue;
                  const float xv = x[static_cast<size_t>(
                      ((b * s.in_channels + i) * s.height + iy) * s.width + ix)];
                  const float wv = w[static_cast<size_t>(
                      ((o * s.in_channels + i) * s.kernel + ky) * s.kernel + kx)];
                  const double p16 =
                      static_cast<double>(round_half(wv * scale, type)) * round_half(xv, type);
                  sum16 += p16;
                  sum32 += static_cast<double>(wv) * scale * xv;
                  magnitude += std::abs(p16);
                }
              }
            }
            const double b_folded = static_cast<double>(scale) * bias[oi] + shift;
            double ref16 = sum16 + b_folded, ref32 = sum32 + b_folded;
            if (cc.relu) ref16 = std::max(0.0, ref16), ref32 = std::max(0.0, ref32);
            const float got =
                y[static_cast<size_t>(((b * s.out_channels + o) * ho + oy) * wo + ox)];
            const double tol = static_cast<double>(k) * 0x1p-24 * (magnitude + std::abs(b_folded)) +
                               0x1p-23 * std::abs(ref16) + 1e-7;
            ASSERT_NEAR(got, ref16, tol)
                << "y[" << b << "][" << o << "][" << oy << "][" << ox << "]";
            const double tol32 = (2 * u + u * u) * magnitude * 1.01 + tol;
            EXPECT_NEAR(got, ref32, tol32);
            worst_vs_fp32 = std::max(worst_vs_fp32, std::abs(got - ref32) / (magnitude + 1e-30));
          }
        }
      }
    }
    ::testing::Test::RecordProperty(split ? "worst_error_vs_fp32_split" : "worst_error_vs_fp32",
                                    std::to_string(worst_vs_fp32));
  }
}

TEST(ConvMma, Conv3x3PaddedBatchNormReluBf16) {
  check_conv({2, 5, 9, 11, 70, 3, 1, true, true}, Half16::BF16);
}
TEST(ConvMma, Conv3x3PaddedF16) {
  check_conv({1, 19, 7, 6, 33, 3, 1, false, false}, Half16::F16);
}
TEST(ConvMma, Conv3x3UnpaddedBf16) {
  check_conv({1, 3, 6, 9, 8, 3, 0, true, false}, Half16::BF16);
}
TEST(ConvMma, Conv1x1HeadBf16) {
  check_conv({2, 40, 5, 13, 12, 1, 0, false, false}, Half16::BF16);
}
TEST(ConvMma, ManyChannelsBf16) {
  check_conv({1, 96, 4, 5, 130, 3, 1, true, true}, Half16::BF16);
}
// One K step (12 channels padded to 32): fewer steps than the pipeline's stages.
TEST(ConvMma, OneKStepBf16) {
  check_conv({1, 12, 3, 50, 20, 1, 0, false, true}, Half16::BF16);
}
// Few tiles and a long K split K (kernels/conv2d_mma.cu, gemm_splits: about 256 blocks, at least
// 8 steps of 32 a split): 20 pixels (one tile) x 130 columns (two) with K = 9 x 96 = 27 steps:
// min(256 / 2, 27 / 8) = 3 splits of 20 x 130 sums; a 3 x 3 convolution of 64 -> 64 channels on
// 400 x 400 pixels has 1,250 tiles: unsplit. The forward of ManyChannelsBf16 runs split.
TEST(ConvMma, SplitsKWhereTheTilesAreFew) {
  EXPECT_EQ(cuda::conv2d_mma_forward_workspace({1, 96, 4, 5, 130, 3, 1}), 3 * 20 * 130);
  EXPECT_EQ(cuda::conv2d_mma_forward_workspace({1, 64, 400, 400, 64, 3, 1}), 0);
  // 12 channels: one K step, nothing to split.
  EXPECT_EQ(cuda::conv2d_mma_forward_workspace({1, 12, 3, 50, 20, 1, 0}), 0);
  // The deepest layer at full size: 31 x 62 pixels (16 tiles) x 1024 columns (8): 128 blocks, 2
  // splits of K = 9 x 1024 (288 steps).
  EXPECT_EQ(cuda::conv2d_mma_forward_workspace({1, 1024, 31, 62, 1024, 3, 1}), 2 * 31 * 62 * 1024);
  // The input gradient of ConvMmaBackward.Conv3x3PaddedBf16: dy's 70 channels (96 padded) x 9
  // taps = 27 steps, 198 pixels (two tiles) x 5 columns (one): 3 splits.
  EXPECT_EQ(cuda::conv2d_mma_backward_data_workspace({2, 5, 9, 11, 70, 3, 1}), 3 * 198 * 5);
}

#if defined(PILLARSEG_CUDA_EMULATION)
// What the emulation counts a convolution issue (Backend::counters' tensor_core_flops and
// async_copy_bytes): every block of 128 pixels x BN columns (BN 64 for at most 64 columns, else
// 128) runs Kp / 32 steps, each 4 warps x (64 x BN / 2) / (16 x 8) x 2 mma.sync m16n8k16 of
// 4,096 flops, so 2 x 128 x BN x Kp flops a block; and copies its BN x 32 16-bit weights a step
// (4 x 16 bytes a row, zero-filled past the last column included).
TEST(ConvMma, EmulationCountsTheIssuedInstructions) {
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
    DeviceBuffer<std::uint16_t> w16(static_cast<size_t>(s.out_channels * c.k_padded));
    DeviceBuffer<float> bias(static_cast<size_t>(s.out_channels));
    DeviceBuffer<float> y(
        static_cast<size_t>(s.batch * s.out_channels * s.out_height() * s.out_width()));
    PS_CUDA_CHECK(cudaMemset(x.data(), 0, x.size() * sizeof(float)));
    PS_CUDA_CHECK(cudaMemset(w16.data(), 0, w16.size() * sizeof(std::uint16_t)));
    PS_CUDA_CHECK(cudaMemset(bias.data(), 0, bias.size() * sizeof(float)));
    ASSERT_EQ(op::half16_weight_k(s.in_channels, s.kernel * s.kernel), c.k_padded);
    const emu::InstructionCounts before = emu::instruction_counts();
    cuda::conv2d_mma_forward(x.data(), false, w16.data(), bias.data(), s, Half16::BF16, false,
                             y.data(), false, nullptr);
    PS_CUDA_CHECK(cudaDeviceSynchronize());
    const emu::InstructionCounts after = emu::instruction_counts();
    const std::int64_t blocks = c.blocks_m * c.blocks_n, steps = c.k_padded / 32;
    EXPECT_EQ(static_cast<std::int64_t>(after.mma_m16n8k16 - before.mma_m16n8k16) * 4096,
              blocks * 2 * 128 * c.bn * c.k_padded)
        << s.out_channels << " columns";
    EXPECT_EQ(static_cast<std::int64_t>(after.cp_async_bytes - before.cp_async_bytes),
              blocks * steps * c.bn * 64)
        << s.out_channels << " columns";
  }
}
#endif

// in_channels 512: K = 16 steps for one tile of 24 pixels x 20 columns: 2 splits with the
// workspace, whose reduction writes the sub-pixels.
void check_transposed(Half16 type, std::int64_t in_channels = 6) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  const std::int64_t B = 2, I = in_channels, O = 5, H = 3, W = 4;
  Rng rng(5);
  const std::vector<float> x = uniform(static_cast<size_t>(B * I * H * W), rng, -2, 2);
  const std::vector<float> w = uniform(static_cast<size_t>(I * O * 4), rng, -0.5, 0.5);
  const std::vector<float> bias = uniform(static_cast<size_t>(O), rng, -1, 1);
  auto dx = DeviceBuffer<float>::from_host(x), dw = DeviceBuffer<float>::from_host(w),
       dbias = DeviceBuffer<float>::from_host(bias);
  DeviceBuffer<std::uint16_t> w16(static_cast<size_t>(4 * O * op::half16_weight_k(I, 1)));
  DeviceBuffer<float> b_out(static_cast<size_t>(4 * O)), dy(static_cast<size_t>(B * O * 4 * H * W));
  cuda::prepare_conv_transpose_weights(dw.data(), dbias.data(), I, O, type, w16.data(),
                                       b_out.data(), nullptr);
  const std::int64_t workspace_floats =
      cuda::conv_transpose2d_mma_forward_workspace(B, I, H, W, O);
  if (I == 512) {
    EXPECT_EQ(workspace_floats, 2 * B * H * W * 4 * O);
  }
  DeviceBuffer<float> workspace(static_cast<size_t>(std::max<std::int64_t>(workspace_floats, 1)));
  cuda::conv_transpose2d_mma_forward(dx.data(), false, w16.data(), b_out.data(), B, I, H, W, O,
                                      type, dy.data(), false, nullptr, workspace.data());
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  const std::vector<float> y = dy.to_host();
  for (std::int64_t b = 0; b < B; ++b)
    for (std::int64_t o = 0; o < O; ++o)
      for (std::int64_t yy = 0; yy < 2 * H; ++yy)
        for (std::int64_t xx = 0; xx < 2 * W; ++xx) {
          double sum = bias[static_cast<size_t>(o)], magnitude = 0;
          for (std::int64_t i = 0; i < I; ++i) {
            const double p =
                static_cast<double>(round_half(
                    w[static_cast<size_t>(((i * O + o) * 2 + yy % 2) * 2 + xx % 2)], type)) *
                round_half(x[static_cast<size_t>(((b * I + i) * H + yy / 2) * W + xx / 2)], type);
            sum += p;
            magnitude += std::abs(p);
          }
          const float got = y[static_cast<size_t>(((b * O + o) * 2 * H + yy) * 2 * W + xx)];
          EXPECT_NEAR(
              got, sum,
              static_cast<double>(I) * 0x1p-24 * magnitude + 0x1p-23 * std::abs(sum) + 1e-7);
        }
}

TEST(ConvMma, Transposed2x2Bf16) {
  check_transposed(Half16::BF16);
}
TEST(ConvMma, Transposed2x2F16) {
  check_transposed(Half16::F16);
}
TEST(ConvMma, Transposed2x2SplitKBf16) {
  check_transposed(Half16::BF16, 512);
}

// ---- training gradients ----

// The gradients of a stride-1 convolution against a double reference on the rounded operands:
// dx (K = O k k terms), dw (K = the B Ho Wo pixels, split over blocks and summed in order), dbias
// (in double); outputs between guard words; two runs give the same bits.
void check_conv_backward(const ConvCase& cc, Half16 type) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  const cuda::Conv2dShape s{cc.batch, cc.in_channels, cc.height, cc.width, cc.out_channels, cc.kernel, cc.pad};
  const std::int64_t kk = s.kernel * s.kernel, ho = s.out_height(), wo = s.out_width();
  Rng rng(23 + static_cast<uint64_t>(cc.out_channels));
  const std::vector<float> x = uniform(static_cast<size_t>(s.batch * s.in_channels * s.height * s.width), rng, -2, 2);
  const std::vector<float> w = uniform(static_cast<size_t>(s.out_channels * s.in_channels * kk), rng, -0.5, 0.5);
  const std::vector<float> g = uniform(static_cast<size_t>(s.batch * s.out_channels * ho * wo), rng, -1, 1);
  auto d_x = DeviceBuffer<float>::from_host(x), d_w = DeviceBuffer<float>::from_host(w),
       d_g = DeviceBuffer<float>::from_host(g);
  DeviceBuffer<std::uint16_t> w16t(
      static_cast<size_t>(s.in_channels * op::half16_weight_k(s.out_channels, kk)));
  DeviceBuffer<float> workspace(static_cast<size_t>(std::max<std::int64_t>(1, cuda::conv2d_mma_backward_weights_workspace(s))));
  // Run 0 unsplit, runs 1 and 2 with the workspace that lets dx's GEMM split K where its tiles
  // are few (the same bits twice).
  DeviceBuffer<float> split(
      static_cast<size_t>(std::max<std::int64_t>(1, cuda::conv2d_mma_backward_data_workspace(s))));
  std::vector<std::vector<float>> runs;
  for (int run = 0; run < 3; ++run) {
    GuardedArray<float> dx(static_cast<std::int64_t>(x.size())), dw(static_cast<std::int64_t>(w.size())),
        db(s.out_channels);
    cuda::prepare_conv_data_weights(d_w.data(), s, type, w16t.data(), nullptr);
    cuda::conv2d_mma_backward_data(d_g.data(), w16t.data(), s, type, dx.data(), nullptr,
                                   run > 0 ? split.data() : nullptr);
    cuda::conv2d_mma_backward_weights(d_x.data(), d_g.data(), s, type, dw.data(), db.data(), workspace.data(),
                                      nullptr);
    PS_CUDA_CHECK(cudaDeviceSynchronize());
    EXPECT_TRUE(dx.guards_intact());
    EXPECT_TRUE(dw.guards_intact());
    EXPECT_TRUE(db.guards_intact());
    std::vector<float> all = dx.download(), part = dw.download(), bias = db.download();
    all.insert(all.end(), part.begin(), part.end());
    all.insert(all.end(), bias.begin(), bias.end());
    runs.push_back(std::move(all));
  }
  EXPECT_EQ(runs[1], runs[2]) << "two runs differ";
  const std::vector<float> unsplit_dx(runs[0].begin(),
                                      runs[0].begin() + static_cast<std::ptrdiff_t>(x.size()));
  const std::vector<float>& got = runs[1];
  const auto at_x = [&](std::int64_t b, std::int64_t i, std::int64_t y, std::int64_t xx) {
    return round_half(x[static_cast<size_t>(((b * s.in_channels + i) * s.height + y) * s.width + xx)], type);
  };
  const auto at_g = [&](std::int64_t b, std::int64_t o, std::int64_t y, std::int64_t xx) {
    return round_half(g[static_cast<size_t>(((b * s.out_channels + o) * ho + y) * wo + xx)], type);
  };
  const auto at_w = [&](std::int64_t o, std::int64_t i, std::int64_t t) {
    return round_half(w[static_cast<size_t>((o * s.in_channels + i) * kk + t)], type);
  };
  // dx, split and unsplit
  for (const std::vector<float>* dx_run : {&got, &unsplit_dx})
    for (std::int64_t b = 0; b < s.batch; ++b)
      for (std::int64_t i = 0; i < s.in_channels; ++i)
        for (std::int64_t y = 0; y < s.height; ++y)
          for (std::int64_t xx = 0; xx < s.width; ++xx) {
            double sum = 0, magnitude = 0;
            for (std::int64_t o = 0; o < s.out_channels; ++o)
              for (std::int64_t t = 0; t < kk; ++t) {
                const std::int64_t oy = y + s.pad - t / s.kernel, ox = xx + s.pad - t % s.kernel;
                if (oy < 0 || oy >= ho || ox < 0 || ox >= wo) continue;
                const double p = static_cast<double>(at_w(o, i, t)) * at_g(b, o, oy, ox);
                sum += p, magnitude += std::abs(p);
              }
            const float v = (*dx_run)[static_cast<size_t>(
                ((b * s.in_channels + i) * s.height + y) * s.width + xx)];
            ASSERT_NEAR(v, sum,
                        static_cast<double>(s.out_channels * kk) * 0x1p-24 * magnitude + 1e-7)
                << "dx[" << b << "][" << i << "][" << y << "][" << xx << "]";
          }
  // dw, dbias
  const size_t dw0 = x.size(), db0 = x.size() + w.size();
  for (std::int64_t o = 0; o < s.out_channels; ++o) {
    double bias_sum = 0, bias_magnitude = 0;
    for (std::int64_t b = 0; b < s.batch; ++b)
      for (std::int64_t oy = 0; oy < ho; ++oy)
        for (std::int64_t ox = 0; ox < wo; ++ox) {
          const double v = g[static_cast<size_t>(((b * s.out_channels + o) * ho + oy) * wo + ox)];
          bias_sum += v, bias_magnitude += std::abs(v);
        }
    ASSERT_NEAR(got[db0 + static_cast<size_t>(o)], bias_sum, 1e-6 * bias_magnitude + 1e-7) << "dbias[" << o << "]";
    for (std::int64_t i = 0; i < s.in_channels; ++i)
      for (std::int64_t t = 0; t < kk; ++t) {
        double sum = 0, magnitude = 0;
        for (std::int64_t b = 0; b < s.batch; ++b)
          for (std::int64_t oy = 0; oy < ho; ++oy)
            for (std::int64_t ox = 0; ox < wo; ++ox) {
              const std::int64_t iy = oy + t / s.kernel - s.pad, ix = ox + t % s.kernel - s.pad;
              if (iy < 0 || iy >= s.height || ix < 0 || ix >= s.width) continue;
              const double p = static_cast<double>(at_g(b, o, oy, ox)) * at_x(b, i, iy, ix);
              sum += p, magnitude += std::abs(p);
            }
        const float v = got[dw0 + static_cast<size_t>((o * s.in_channels + i) * kk + t)];
        ASSERT_NEAR(v, sum, static_cast<double>(s.batch * ho * wo) * 0x1p-24 * magnitude + 1e-7)
            << "dw[" << o << "][" << i << "][" << t << "]";
      }
  }
}

TEST(ConvMmaBackward, Conv3x3PaddedBf16) {
  check_conv_backward({2, 5, 9, 11, 70, 3, 1, false, false}, Half16::BF16);
}
TEST(ConvMmaBackward, Conv3x3PaddedF16) {
  check_conv_backward({1, 19, 7, 6, 33, 3, 1, false, false}, Half16::F16);
}
TEST(ConvMmaBackward, Conv3x3UnpaddedBf16) {
  check_conv_backward({1, 3, 6, 9, 8, 3, 0, false, false}, Half16::BF16);
}
TEST(ConvMmaBackward, Conv1x1HeadBf16) {
  check_conv_backward({2, 40, 5, 13, 12, 1, 0, false, false}, Half16::BF16);
}
// 37 x 41 pixels: the weight gradient splits them over 48 blocks, the last one short.
TEST(ConvMmaBackward, ManyPixelsSplitBf16) {
  check_conv_backward({1, 4, 37, 41, 4, 3, 1, false, false}, Half16::BF16);
}

void check_transposed_backward(std::int64_t B, std::int64_t I, std::int64_t O, std::int64_t H, std::int64_t W,
                               Half16 type) {
  std::string why;
  if (!cuda::mma_supported(&why)) GTEST_SKIP() << why;
  const cuda::ConvTranspose2dShape s{B, I, H, W, O};
  Rng rng(7 + static_cast<uint64_t>(I));
  const std::vector<float> x = uniform(static_cast<size_t>(B * I * H * W), rng, -2, 2);
  const std::vector<float> w = uniform(static_cast<size_t>(I * O * 4), rng, -0.5, 0.5);
  const std::vector<float> g = uniform(static_cast<size_t>(B * O * 4 * H * W), rng, -1, 1);
  auto d_x = DeviceBuffer<float>::from_host(x), d_w = DeviceBuffer<float>::from_host(w),
       d_g = DeviceBuffer<float>::from_host(g);
  DeviceBuffer<std::uint16_t> w16t(static_cast<size_t>(I * op::half16_weight_k(O, 4)));
  DeviceBuffer<float> workspace(
      static_cast<size_t>(std::max<std::int64_t>(1, cuda::conv_transpose2d_mma_backward_weights_workspace(s))));
  GuardedArray<float> dx(static_cast<std::int64_t>(x.size())), dw(static_cast<std::int64_t>(w.size())), db(O);
  cuda::prepare_conv_transpose_data_weights(d_w.data(), s, type, w16t.data(), nullptr);
  cuda::conv_transpose2d_mma_backward_data(d_g.data(), w16t.data(), s, type, dx.data(), nullptr);
  cuda::conv_transpose2d_mma_backward_weights(d_x.data(), d_g.data(), s, type, dw.data(), db.data(),
                                               workspace.data(), nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  EXPECT_TRUE(dx.guards_intact());
    EXPECT_TRUE(dw.guards_intact());
    EXPECT_TRUE(db.guards_intact());
  const std::vector<float> gx = dx.download(), gw = dw.download(), gb = db.download();
  const auto at_g = [&](std::int64_t b, std::int64_t o, std::int64_t y, std::int64_t xx) {
    return round_half(g[static_cast<size_t>(((b * O + o) * 2 * H + y) * 2 * W + xx)], type);
  };
  for (std::int64_t b = 0; b < B; ++b)
    for (std::int64_t i = 0; i < I; ++i)
      for (std::int64_t y = 0; y < H; ++y)
        for (std::int64_t xx = 0; xx < W; ++xx) {
          double sum = 0, magnitude = 0;
          for (std::int64_t o = 0; o < O; ++o)
            for (std::int64_t sub = 0; sub < 4; ++sub) {
              const double p = static_cast<double>(round_half(w[static_cast<size_t>((i * O + o) * 4 + sub)], type)) *
                               at_g(b, o, 2 * y + sub / 2, 2 * xx + sub % 2);
              sum += p, magnitude += std::abs(p);
            }
          ASSERT_NEAR(gx[static_cast<size_t>(((b * I + i) * H + y) * W + xx)], sum,
                      static_cast<double>(4 * O) * 0x1p-24 * magnitude + 1e-7)
              << "dx[" << b << "][" << i << "][" << y << "][" << xx << "]";
        }
  for (std::int64_t i = 0; i < I; ++i)
    for (std::int64_t o = 0; o < O; ++o)
      for (std::int64_t sub = 0; sub < 4; ++sub) {
        double sum = 0, magnitude = 0;
        for (std::int64_t b = 0; b < B; ++b)
          for (std::int64_t y = 0; y < H; ++y)
            for (std::int64_t xx = 0; xx < W; ++xx) {
              const double p =
                  static_cast<double>(round_half(x[static_cast<size_t>(((b * I + i) * H + y) * W + xx)], type)) *
                  at_g(b, o, 2 * y + sub / 2, 2 * xx + sub % 2);
              sum += p, magnitude += std::abs(p);
            }
        ASSERT_NEAR(gw[static_cast<size_t>((i * O + o) * 4 + sub)], sum,
                    static_cast<double>(B * H * W) * 0x1p-24 * magnitude + 1e-7)
            << "dw[" << i << "][" << o << "][" << sub << "]";
      }
  for (std::int64_t o = 0; o < O; ++o) {
    double sum = 0, magnitude = 0;
    for (std::int64_t b = 0; b < B; ++b)
      for (std::int64_t p = 0; p < 4 * H * W; ++p) {
        const double v = g[static_cast<size_t>((b * O + o) * 4 * H * W + p)];
        sum += v, magnitude += std::abs(v);
      }
    ASSERT_NEAR(gb[static_cast<size_t>(o)], sum, 1e-6 * magnitude + 1e-7) << "dbias[" << o << "]";
  }
}

TEST(ConvMmaBackward, Transposed2x2Bf16) {
  check_transposed_backward(2, 6, 5, 3, 4, Half16::BF16);
}
TEST(ConvMmaBackward, Transposed2x2ManyChannelsF16) {
  check_transposed_backward(1, 70, 17, 5, 7, Half16::F16);
}

// ---- 16-bit activations ----

std::vector<std::uint16_t> half_bits(const std::vector<float>& v, Half16 type) {
  std::vector<std::uint16_t> bits(v.size());
  for (size_t i = 0; i < v.size(); ++i)
    bits[i] = type == Half16::BF16 ? cuda::float_to_bf16_bits(v[i]) : cuda::float_to_f16_bits(v[i]);
  return bits;
}
std::vector<float> half_values(const std::vector<std::uint16_t>& bits, Half16 type) {
  std::vector<float> v(bits.size());
  for (size_t i = 0; i < v.size(); ++i)
    v[i] =
        type == Half16::BF16 ? cuda::bf16_bits_to_float(bits[i]) : cuda::f16_bits_to_float(bits[i]);
  return v;
}
// |a - b| within one rounding of b to the 16-bit type (unit roundoff u of its magnitude).
void expect_within_one_rounding(const std::vector<float>& a, const std::vector<float>& b,
                                Half16 type, const char* what) {
  ASSERT_EQ(a.size(), b.size());
  const double u = type == Half16::BF16 ? 0x1p-8 : 0x1p-11;
  for (size_t i = 0; i < a.size(); ++i)
    ASSERT_LE(std::abs(static_cast<double>(a[i]) - b[i]),
              u * std::abs(static_cast<double>(b[i])) * 1.0001 + 1e-30)
        << what << " element " << i << ": " << a[i] << " vs " << b[i];
}

void check_half_ops(Half16 type) {
  const std::int64_t B = 2, C = 3, H = 7, W = 10, planes = B * C;
  Rng rng(77);
  const std::vector<float> raw = uniform(static_cast<size_t>(planes * H * W), rng, -3, 3);
  const std::vector<std::uint16_t> bits = half_bits(raw, type);
  const std::vector<float> rounded = half_values(bits, type);
  auto d_bits = DeviceBuffer<std::uint16_t>::from_host(bits);
  auto d_rounded = DeviceBuffer<float>::from_host(rounded);
  auto d_raw = DeviceBuffer<float>::from_host(raw);

  // to_half16 rounds like the host.
  DeviceBuffer<std::uint16_t> converted(bits.size());
  cuda::to_half16(d_raw.data(), static_cast<std::int64_t>(raw.size()), type, converted.data(),
                  nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  EXPECT_EQ(converted.to_host(), bits);

  // Max-pool: the FP32 kernel on the rounded values, exactly.
  const size_t pooled = static_cast<size_t>(planes * (H / 2) * (W / 2));
  DeviceBuffer<std::uint16_t> pool16(pooled);
  DeviceBuffer<float> pool32(pooled);
  DeviceBuffer<std::int32_t> argmax(pooled);
  cuda::maxpool2d_half16(d_bits.data(), planes, H, W, type, pool16.data(), nullptr);
  cuda::maxpool2d_forward(d_rounded.data(), planes, H, W, pool32.data(), argmax.data(), nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  EXPECT_EQ(half_values(pool16.to_host(), type), pool32.to_host());

  // Upsampling: within one rounding of the FP32 kernel's result on the rounded values.
  const size_t up = static_cast<size_t>(planes * 4 * H * W);
  DeviceBuffer<std::uint16_t> up16(up);
  DeviceBuffer<float> up32(up);
  cuda::upsample_bilinear_half16(d_bits.data(), planes, H, W, type, up16.data(), nullptr);
  cuda::upsample_bilinear_forward(d_rounded.data(), planes, H, W, up32.data(), nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  expect_within_one_rounding(half_values(up16.to_host(), type), up32.to_host(), type, "upsample");

  // Zero-padded concatenation of skip (B, 3, 7, 10) and up (B, 2, 4, 6), and a channel copy.
  const std::vector<float> up_raw = uniform(static_cast<size_t>(B * 2 * 4 * 6), rng, -3, 3);
  const std::vector<std::uint16_t> up_bits = half_bits(up_raw, type);
  auto d_up_bits = DeviceBuffer<std::uint16_t>::from_host(up_bits);
  auto d_up_rounded = DeviceBuffer<float>::from_host(half_values(up_bits, type));
  const cuda::PadConcatShape shape{B, C, 2, H, W, 4, 6};
  const size_t joined = static_cast<size_t>(B * 5 * H * W);
  DeviceBuffer<std::uint16_t> cat16(joined);
  DeviceBuffer<float> cat32(joined);
  cuda::pad_concat_half16(d_bits.data(), d_up_bits.data(), shape, cat16.data(), nullptr);
  cuda::pad_concat_forward(d_rounded.data(), d_up_rounded.data(), shape, cat32.data(), nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  EXPECT_EQ(half_values(cat16.to_host(), type), cat32.to_host());
  const cuda::ChannelBand band{B, C, H * W, 5, 2};
  std::vector<std::uint16_t> wide(joined, 0x1234);
  auto d_wide = DeviceBuffer<std::uint16_t>::from_host(wide);
  cuda::copy_channels_half16(d_bits.data(), band, d_wide.data(), nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  const std::vector<std::uint16_t> got = d_wide.to_host();
  for (std::int64_t b = 0; b < B; ++b)
    for (std::int64_t c = 0; c < 5; ++c)
      for (std::int64_t p = 0; p < H * W; ++p) {
        const std::uint16_t expected =
            c >= 2 ? bits[static_cast<size_t>((b * C + c - 2) * H * W + p)] : std::uint16_t{0x1234};
        ASSERT_EQ(got[static_cast<size_t>((b * 5 + c) * H * W + p)], expected)
            << b << " " << c << " " << p;
      }

  // A convolution with 16-bit input and output against FP32 input and output on the same values.
  const cuda::Conv2dShape s{B, C, H, W, 9, 3, 1};
  const std::vector<float> w = uniform(static_cast<size_t>(9 * C * 9), rng, -0.5, 0.5);
  const std::vector<float> bias = uniform(9, rng, -1, 1);
  auto dw = DeviceBuffer<float>::from_host(w), dbias = DeviceBuffer<float>::from_host(bias);
  DeviceBuffer<std::uint16_t> w16(static_cast<size_t>(9 * op::half16_weight_k(C, 9)));
  DeviceBuffer<float> b_out(9);
  cuda::prepare_conv_weights(dw.data(), dbias.data(), cuda::FoldedBatchNorm{}, s, type, w16.data(),
                             b_out.data(), nullptr);
  const size_t outputs = static_cast<size_t>(B * 9 * H * W);
  DeviceBuffer<std::uint16_t> y16(outputs);
  DeviceBuffer<float> y32(outputs);
  cuda::conv2d_mma_forward(d_bits.data(), true, w16.data(), b_out.data(), s, type, true, y16.data(),
                           true, nullptr);
  cuda::conv2d_mma_forward(d_rounded.data(), false, w16.data(), b_out.data(), s, type, true,
                           y32.data(), false, nullptr);
  PS_CUDA_CHECK(cudaDeviceSynchronize());
  const std::vector<float> y32_host = y32.to_host();
  EXPECT_EQ(half_bits(y32_host, type), y16.to_host())
      << "the 16-bit output is the FP32 one rounded once";
}

TEST(HalfOps, MatchTheFp32KernelsOnRoundedValuesBf16) {
  check_half_ops(Half16::BF16);
}
TEST(HalfOps, MatchTheFp32KernelsOnRoundedValuesF16) {
  check_half_ops(Half16::F16);
}

}  // namespace
