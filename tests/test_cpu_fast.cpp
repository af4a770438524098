// The CPU fast paths against the host/ reference they replace: the Winograd F(4x4, 3x3)
// convolution (forward with its epilogue, input and weight gradients) against host::conv2d at
// odd shapes, and the same bits for any thread count; the PFN per block of pillars
// (engine/cpu/pfn_blocked) against host/pfn, also with synchronised BatchNorm's replica sums.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <tuple>
#include <vector>

#include "core/bf16.hpp"
#include "core/error.hpp"
#include "core/parallel.hpp"
#include "core/replicas.hpp"
#include "core/rng.hpp"
#include "engine/cpu/pfn_blocked.hpp"
#include "host/conv2d.hpp"
#include "host/conv2d_winograd.hpp"
#include "host/pfn.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using pillarseg::test::random_tensor;

namespace {

// F(4x4, 3x3) in float adds the rounding of its transforms (entries up to 5 in B^T, 8 in A^T)
// to the reference's: a few 1e-6 of the typical size sqrt(9 I) of a sum of 9 I products of
// values in [-1, 1).
double winograd_atol(int64_t summed_channels) {
  return 1e-5 * std::sqrt(9.0 * static_cast<double>(summed_channels));
}
constexpr double kRtol = 1e-4;

// (B, I, H, W, O): sizes not multiples of the 4x4 tile, single pixels and rows, more than
// one block; with I + O >= 456 the blocks run in shared phases instead of one per thread.
using ConvCase = std::tuple<int64_t, int64_t, int64_t, int64_t, int64_t>;

class WinogradConv : public ::testing::TestWithParam<ConvCase> {};

TEST_P(WinogradConv, ForwardMatchesReferenceWithBiasEpilogue) {
  const auto [B, I, H, W, O] = GetParam();
  Rng rng(static_cast<uint64_t>(B * 1000 + I * 100 + H * 10 + W + O));
  const Tensor<float> x = random_tensor<float>({B, I, H, W}, rng);
  const Tensor<float> w = random_tensor<float>({O, I, 3, 3}, rng);
  const Tensor<float> bias = random_tensor<float>({O}, rng);
  Tensor<float> expected, actual;
  host::conv2d_forward(x, w, &bias, 1, expected);
  host::WinogradWorkspace ws;
  host::conv3x3_winograd_forward(x, w, {nullptr, bias.data(), false}, actual, ws);
  EXPECT_TRUE(test::all_close(actual, expected, winograd_atol(I), kRtol));
}

TEST_P(WinogradConv, ScaleShiftReluEpilogueIsBatchNormOfTheReference) {
  const auto [B, I, H, W, O] = GetParam();
  Rng rng(static_cast<uint64_t>(7 + B + I + H + W + O));
  const Tensor<float> x = random_tensor<float>({B, I, H, W}, rng);
  const Tensor<float> w = random_tensor<float>({O, I, 3, 3}, rng);
  const Tensor<float> scale = random_tensor<float>({O}, rng, 0.5, 2);
  const Tensor<float> shift = random_tensor<float>({O}, rng);
  Tensor<float> conv, actual;
  host::conv2d_forward(x, w, nullptr, 1, conv);
  Tensor<float> expected(conv.shape());
  for (int64_t b = 0; b < B; ++b)
    for (int64_t o = 0; o < O; ++o)
      for (int64_t y = 0; y < H; ++y)
        for (int64_t xx = 0; xx < W; ++xx)
          expected(b, o, y, xx) = std::max(conv(b, o, y, xx) * scale[o] + shift[o], 0.0f);
  host::WinogradWorkspace ws;
  host::conv3x3_winograd_forward(x, w, {scale.data(), shift.data(), true}, actual, ws);
  EXPECT_TRUE(test::all_close(actual, expected, 2 * winograd_atol(I), kRtol));
}

// On activations stored as BF16 bits: each input widened exactly, the same FP32 arithmetic, each
// output rounded to nearest even once, so bit for bit the FP32 convolution of the widened input,
// rounded.
TEST_P(WinogradConv, Bf16ActivationsAreTheFp32ConvolutionOfTheWidenedInputRounded) {
  const auto [B, I, H, W, O] = GetParam();
  Rng rng(static_cast<uint64_t>(19 + B + I + H + W + O));
  const Tensor<float> xf = random_tensor<float>({B, I, H, W}, rng);
  const Tensor<float> w = random_tensor<float>({O, I, 3, 3}, rng);
  const Tensor<float> shift = random_tensor<float>({O}, rng);
  Tensor<uint16_t> x(xf.shape());
  Tensor<float> widened(xf.shape());
  for (int64_t i = 0; i < xf.numel(); ++i) {
    x.data()[i] = float_to_bf16_bits(xf.data()[i]);
    widened.data()[i] = bf16_bits_to_float(x.data()[i]);
  }
  for (const bool relu : {false, true}) {
    host::WinogradWorkspace ws;
    Tensor<float> expected;
    Tensor<uint16_t> actual;
    host::conv3x3_winograd_forward(widened, w, {nullptr, shift.data(), relu}, expected, ws);
    host::conv3x3_winograd_forward(x, w, {nullptr, shift.data(), relu}, actual, ws);
    ASSERT_EQ(actual.shape(), expected.shape());
    int64_t rounded_away = 0;
    for (int64_t i = 0; i < expected.numel(); ++i) {
      ASSERT_EQ(actual.data()[i], float_to_bf16_bits(expected.data()[i])) << "element " << i << ", relu " << relu;
      rounded_away += bf16_bits_to_float(actual.data()[i]) != expected.data()[i];
    }
    if (expected.numel() > 8) {
      EXPECT_GT(rounded_away, 0) << "the outputs must be rounded to BF16";
    }
  }
}

// dx sums O 9 products per value; dw sums B H W products per weight, in float in both paths.
TEST_P(WinogradConv, InputAndWeightGradientsMatchReference) {
  const auto [B, I, H, W, O] = GetParam();
  Rng rng(static_cast<uint64_t>(31 + B + I + H + W + O));
  const Tensor<float> x = random_tensor<float>({B, I, H, W}, rng);
  const Tensor<float> w = random_tensor<float>({O, I, 3, 3}, rng);
  const Tensor<float> dy = random_tensor<float>({B, O, H, W}, rng);
  Tensor<float> expected_dx, expected_dw, dx, dw;
  host::conv2d_backward(x, w, dy, 1, &expected_dx, &expected_dw, nullptr);
  host::WinogradWorkspace ws;
  host::conv3x3_winograd_input_gradient(dy, w, dx, ws);
  host::conv3x3_winograd_weight_gradient(x, dy, dw, ws);
  EXPECT_TRUE(test::all_close(dx, expected_dx, winograd_atol(O), kRtol));
  EXPECT_TRUE(
      test::all_close(dw, expected_dw, 2e-5 * std::sqrt(static_cast<double>(B * H * W)), kRtol));

  // As the executor passes its outputs (test::StaleView), with the workspace left by another
  // convolution (its forward): every element written, the same bits.
  test::StaleView<float> y_view({B, O, H, W}), dx_view(dx.shape()), dw_view(dw.shape());
  Tensor<float> y;
  host::conv3x3_winograd_forward(x, w, {}, y, ws);
  host::conv3x3_winograd_forward(x, w, {}, y_view.tensor, ws);
  host::conv3x3_winograd_input_gradient(dy, w, dx_view.tensor, ws);
  host::conv3x3_winograd_weight_gradient(x, dy, dw_view.tensor, ws);
  EXPECT_TRUE(test::all_close(y_view.tensor, y, 0, 0));
  EXPECT_TRUE(test::all_close(dx_view.tensor, dx, 0, 0));
  EXPECT_TRUE(test::all_close(dw_view.tensor, dw, 0, 0));
}

INSTANTIATE_TEST_SUITE_P(Shapes, WinogradConv,
                         ::testing::Values(ConvCase{1, 1, 1, 1, 1}, ConvCase{2, 3, 7, 9, 5},
                                           ConvCase{1, 4, 1, 13, 3}, ConvCase{1, 5, 13, 1, 2},
                                           ConvCase{2, 16, 33, 17, 8}, ConvCase{1, 8, 4, 4, 8},
                                           ConvCase{1, 40, 70, 9, 24},
                                           ConvCase{1, 300, 9, 22, 170}));

// Large enough to run in parallel and in several blocks, in both schedules (blocks per thread:
// 48 + 40 channels; shared phases: 300 + 200); the bits must not depend on threads.
class WinogradThreads : public ::testing::TestWithParam<ConvCase> {};

TEST_P(WinogradThreads, SameBitsForAnyThreadCount) {
  const auto [B, I, H, W, O] = GetParam();
  Rng rng(5);
  const Tensor<float> x = random_tensor<float>({B, I, H, W}, rng);
  const Tensor<float> w = random_tensor<float>({O, I, 3, 3}, rng);
  const Tensor<float> shift = random_tensor<float>({O}, rng);
  const int saved = num_threads();
  Tensor<float> one, two, dx_one, dx_two, dw_one, dw_two;
  host::WinogradWorkspace ws;
  set_num_threads(1);
  host::conv3x3_winograd_forward(x, w, {nullptr, shift.data(), true}, one, ws);
  host::conv3x3_winograd_input_gradient(one, w, dx_one, ws);
  host::conv3x3_winograd_weight_gradient(x, one, dw_one, ws);
  set_num_threads(2);
  host::conv3x3_winograd_forward(x, w, {nullptr, shift.data(), true}, two, ws);
  host::conv3x3_winograd_input_gradient(two, w, dx_two, ws);
  host::conv3x3_winograd_weight_gradient(x, two, dw_two, ws);
  set_num_threads(saved);
  EXPECT_EQ(one, two);
  EXPECT_EQ(dx_one, dx_two);
  EXPECT_EQ(dw_one, dw_two);
}

INSTANTIATE_TEST_SUITE_P(Schedules, WinogradThreads,
                         ::testing::Values(ConvCase{1, 48, 150, 61, 40},
                                           ConvCase{2, 300, 30, 41, 200}));

TEST(WinogradConv, RejectsWrongShapes) {
  host::WinogradWorkspace ws;
  Tensor<float> y;
  EXPECT_THROW(host::conv3x3_winograd_forward(Tensor<float>({1, 3, 4, 4}),
                                              Tensor<float>({2, 4, 3, 3}), {}, y, ws),
               Error);
  EXPECT_THROW(host::conv3x3_winograd_forward(Tensor<float>({1, 3, 4, 4}),
                                              Tensor<float>({2, 3, 1, 1}), {}, y, ws),
               Error);
  EXPECT_THROW(host::conv3x3_winograd_input_gradient(Tensor<float>({1, 3, 4, 4}),
                                                     Tensor<float>({2, 3, 3, 3}), y, ws),
               Error);
  // dy must match x in batch and image size.
  EXPECT_THROW(host::conv3x3_winograd_weight_gradient(Tensor<float>({1, 3, 4, 4}),
                                                      Tensor<float>({1, 2, 4, 5}), y, ws),
               Error);
  EXPECT_THROW(host::conv3x3_winograd_weight_gradient(Tensor<float>({2, 3, 4, 4}),
                                                      Tensor<float>({1, 2, 4, 4}), y, ws),
               Error);
}

}  // namespace

namespace {

// ---- the PFN per block of pillars ----

template <class T>
RefT<T> ref_of(Tensor<T>& t) {
  return {t.data(), t.shape()};
}

// P pillars of N slots with 1..N points each (the rest zero rows, as decorated pillars are),
// weight (C, 10), BatchNorm parameters and running statistics, and the gradient reaching out.
struct PfnCase {
  Tensor<float> points, weight, gamma, beta, running_mean, running_var, dout;
  PfnCase(int64_t P, int64_t N, int64_t C, uint64_t seed) {
    Rng rng(seed);
    points = random_tensor<float>({P, N, 10}, rng, -2, 2);
    for (int64_t p = 0; p < P; ++p) {
      const int64_t kept = 1 + static_cast<int64_t>(rng.uniform(0, static_cast<double>(N)));
      for (int64_t i = std::min(kept, N) * 10; i < N * 10; ++i) points[p * N * 10 + i] = 0.0f;
    }
    weight = random_tensor<float>({C, 10}, rng);
    gamma = random_tensor<float>({C}, rng, 0.5, 1.5);
    beta = random_tensor<float>({C}, rng, -0.5, 0.5);
    running_mean = random_tensor<float>({C}, rng);
    running_var = random_tensor<float>({C}, rng, 0.5, 2);
    dout = random_tensor<float>({P, C}, rng);
  }
};

// What a training forward and its backward give.
struct PfnResults {
  Tensor<float> out, mean, inv_std, running_mean, running_var, dweight, dgamma, dbeta;
  Tensor<int32_t> argmax;
};

PfnResults blocked_pfn(const PfnCase& c, ReplicaSum* replicas = nullptr) {
  const int64_t P = c.points.dim(0), C = c.weight.dim(0);
  PfnResults r{Tensor<float>({P, C}), Tensor<float>({C}), Tensor<float>({C}),
               c.running_mean,        c.running_var,      Tensor<float>({C, 10}),
               Tensor<float>({C}),    Tensor<float>({C}), Tensor<int32_t>({P, C})};
  Tensor<float> points = c.points, weight = c.weight, gamma = c.gamma, beta = c.beta, dout = c.dout;
  BatchNormRefs bn{ref_of(gamma),         ref_of(beta),   ref_of(r.running_mean),
                   ref_of(r.running_var), ref_of(r.mean), ref_of(r.inv_std)};
  bn.eps = 1e-3f, bn.momentum = 0.01f, bn.replicas = replicas;
  IRef argmax = ref_of(r.argmax);
  Ref out = ref_of(r.out), dweight = ref_of(r.dweight), dgamma = ref_of(r.dgamma),
      dbeta = ref_of(r.dbeta);
  cpu::pfn_forward_train(ref_of(points), ref_of(weight), bn, argmax, out);
  cpu::pfn_backward(ref_of(points), ref_of(weight), bn, argmax, ref_of(dout), dweight, dgamma,
                    dbeta);
  return r;
}

PfnResults reference_pfn(const PfnCase& c, ReplicaSum* replicas = nullptr) {
  PfnResults r;
  r.running_mean = c.running_mean, r.running_var = c.running_var;
  int64_t batches = 0;
  host::PfnSaved<float> saved;
  host::BatchNormOptions options{static_cast<double>(1e-3f), static_cast<double>(0.01f), replicas};
  host::pfn_forward_train(c.points, c.weight, c.gamma, c.beta, options, r.running_mean,
                          r.running_var, batches, r.out, saved);
  Tensor<float> d_points;
  host::pfn_backward(c.dout, c.points, c.weight, c.gamma, saved, d_points, r.dweight, r.dgamma,
                     r.dbeta, static_cast<float*>(nullptr), replicas);
  r.mean = saved.norm.mean, r.inv_std = saved.norm.inv_std, r.argmax = saved.max_slot;
  return r;
}

// The size of the terms of dweight(c, d) = sum_r dz(r, c) x(r, d), with dz = s (g - mean_g - xhat
// mean_g_xhat) of BatchNorm's backward (s = gamma inv_std, g the routed gradient, xhat the
// normalised linear output): the largest over (c, d) of sum_r |s| (|g| + |mean_g| + |xhat|
// |mean_g_xhat|) |x(r, d)|. dz cancels (its sum over the rows is 0 by construction), so dweight
// may be far smaller than its terms; its float roundings are a few 2^-24 of them.
double dweight_term_scale(const PfnCase& c, const PfnResults& ref) {
  const int64_t P = c.points.dim(0), N = c.points.dim(1), C = c.weight.dim(0);
  double largest = 0;
  for (int64_t ch = 0; ch < C; ++ch) {
    const double mean = ref.mean[ch], inv_std = ref.inv_std[ch],
                 s = std::abs(c.gamma[ch] * inv_std);
    const auto xhat = [&](int64_t p, int64_t n) {
      double z = 0;
      for (int64_t d = 0; d < 10; ++d)
        z += double{c.points[(p * N + n) * 10 + d]} * c.weight[ch * 10 + d];
      return (z - mean) * inv_std;
    };
    double sum_g = 0, sum_g_xhat = 0;
    for (int64_t p = 0; p < P; ++p) {
      const int32_t slot = ref.argmax[p * C + ch];
      if (slot < 0) continue;
      sum_g += c.dout[p * C + ch];
      sum_g_xhat += c.dout[p * C + ch] * xhat(p, slot);
    }
    const double mean_g = std::abs(sum_g) / static_cast<double>(P * N);
    const double mean_g_xhat = std::abs(sum_g_xhat) / static_cast<double>(P * N);
    std::vector<double> terms(10, 0.0);
    for (int64_t p = 0; p < P; ++p) {
      for (int64_t n = 0; n < N; ++n) {
        const double g = ref.argmax[p * C + ch] == n ? std::abs(double{c.dout[p * C + ch]}) : 0.0;
        const double dz = s * (g + mean_g + std::abs(xhat(p, n)) * mean_g_xhat);
        for (int64_t d = 0; d < 10; ++d) terms[d] += dz * std::abs(c.points[(p * N + n) * 10 + d]);
      }
    }
    for (double t : terms) largest = std::max(largest, t);
  }
  return largest;
}

// The reference sums z in one pass over all rows and dweight in one float GEMM; the blocks sum
// per block (in double) and then in order, so results differ by float rounding: statistics by a
// few float ulps, dweight by ~1e-6 of the size of its terms.
void expect_pfn_close(const PfnCase& c, const PfnResults& got, const PfnResults& ref) {
  EXPECT_TRUE(test::all_close(got.mean, ref.mean, 1e-6, 1e-6));
  EXPECT_TRUE(test::all_close(got.inv_std, ref.inv_std, 0, 1e-6));
  EXPECT_TRUE(test::all_close(got.running_mean, ref.running_mean, 1e-6, 1e-6));
  EXPECT_TRUE(test::all_close(got.running_var, ref.running_var, 0, 1e-6));
  EXPECT_TRUE(test::all_close(got.out, ref.out, 1e-5, 1e-5));
  EXPECT_EQ(got.argmax, ref.argmax);
  EXPECT_TRUE(test::all_close(got.dweight, ref.dweight, 1e-5 * dweight_term_scale(c, ref), 1e-5));
  EXPECT_TRUE(test::all_close(got.dgamma, ref.dgamma, 1e-5, 1e-5));
  EXPECT_TRUE(test::all_close(got.dbeta, ref.dbeta, 1e-5, 1e-5));
}

// Two replicas holding the same batch: every sum doubles. Records the sizes of the sums asked
// for, which every replica must ask in the same order.
class TwinReplicas final : public ReplicaSum {
 public:
  void sum(double* values, int64_t n) override {
    for (int64_t i = 0; i < n; ++i) values[i] *= 2;
    sizes.push_back(n);
  }
  std::vector<int64_t> sizes;
};

}  // namespace

TEST(CpuPfn, TrainingForwardAndBackwardMatchTheReference) {
  for (const auto& [P, N, C] :
       {std::tuple<int64_t, int64_t, int64_t>{100, 20, 64}, {33, 7, 5}, {1, 3, 2}}) {
    SCOPED_TRACE(testing::Message() << "P " << P << " N " << N << " C " << C);
    const PfnCase c(P, N, C, 7);
    expect_pfn_close(c, blocked_pfn(c), reference_pfn(c));
  }
}

TEST(CpuPfn, SameBitsForAnyThreadCount) {
  const PfnCase c(301, 20, 64, 11);
  const int saved = num_threads();
  set_num_threads(1);
  const PfnResults one = blocked_pfn(c);
  set_num_threads(2);
  const PfnResults two = blocked_pfn(c);
  set_num_threads(saved);
  EXPECT_EQ(one.out, two.out);
  EXPECT_EQ(one.argmax, two.argmax);
  EXPECT_EQ(one.running_var, two.running_var);
  EXPECT_EQ(one.dweight, two.dweight);
  EXPECT_EQ(one.dgamma, two.dgamma);
}

// Synchronised BatchNorm: the same sums asked for as the reference asks, and with two replicas
// of the same batch the statistics of the doubled batch: the same mean, variance and dz (so the
// same out and dweight), the running variance's unbiased factor of 2 P N values.
TEST(CpuPfn, ReplicaSumsAsTheReference) {
  const PfnCase c(70, 20, 16, 3);
  TwinReplicas blocked_twins, reference_twins;
  const PfnResults twins = blocked_pfn(c, &blocked_twins);
  expect_pfn_close(c, twins, reference_pfn(c, &reference_twins));
  EXPECT_EQ(blocked_twins.sizes, reference_twins.sizes);
  EXPECT_EQ(blocked_twins.sizes, (std::vector<int64_t>{1, 16, 16, 2 * 16 + 1}));
  const PfnResults alone = blocked_pfn(c);
  EXPECT_TRUE(test::all_close(twins.out, alone.out, 1e-6, 1e-6));
  EXPECT_TRUE(test::all_close(twins.dweight, alone.dweight, 1e-6, 1e-5));
  EXPECT_EQ(twins.dgamma, alone.dgamma);  // each replica's own share
  const double n = 70 * 20;
  for (int64_t k = 0; k < 16; ++k) {
    const double variance = 1.0 / (double{alone.inv_std[k]} * alone.inv_std[k]) - 1e-3;
    const double expected = 0.99 * c.running_var[k] + 0.01 * variance * (2 * n) / (2 * n - 1);
    EXPECT_NEAR(twins.running_var[k], expected, 1e-5 * expected) << "channel " << k;
  }
}

TEST(CpuPfn, NoPillarsLeavesTheRunningStatistics) {
  const PfnCase c(0, 20, 8, 1);
  const PfnResults r = blocked_pfn(c);
  EXPECT_EQ(r.running_mean, c.running_mean);
  EXPECT_EQ(r.running_var, c.running_var);
  EXPECT_EQ(r.dweight, Tensor<float>({8, 10}));
  EXPECT_EQ(r.dgamma, Tensor<float>({8}));
}

TEST(CpuPfn, RejectsAnArgmaxThatIsNoSlot) {
  PfnCase c(40, 4, 3, 5);
  Tensor<float> out({40, 3}), mean({3}), inv_std({3}), dweight({3, 10}), dgamma({3}), dbeta({3});
  Tensor<int32_t> argmax({40, 3});
  BatchNormRefs bn{ref_of(c.gamma),       ref_of(c.beta), ref_of(c.running_mean),
                   ref_of(c.running_var), ref_of(mean),   ref_of(inv_std)};
  IRef am = ref_of(argmax);
  Ref o = ref_of(out), dw = ref_of(dweight), dg = ref_of(dgamma), db = ref_of(dbeta);
  cpu::pfn_forward_train(ref_of(c.points), ref_of(c.weight), bn, am, o);
  argmax[35 * 3 + 2] = 4;
  const std::string message = test::error_of([&] {
    cpu::pfn_backward(ref_of(c.points), ref_of(c.weight), bn, am, ref_of(c.dout), dw, dg, db);
  });
  EXPECT_NE(message.find("argmax(35, 2) = 4 is neither -1 nor a slot of N = 4"), std::string::npos)
      << message;
  EXPECT_NE(test::error_of([&] {
              Tensor<float> wrong({40, 4});
              Ref w = ref_of(wrong);
              cpu::pfn_forward_train(ref_of(c.points), ref_of(c.weight), bn, am, w);
            }).find("pfn_forward"),
            std::string::npos);
}
