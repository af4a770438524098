// The CPU fast paths against the host/ reference they replace: the Winograd F(4x4, 3x3)
// convolution (forward with its epilogue, input and weight gradients) against host::conv2d at
// odd shapes, and the same bits for any thread count.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <tuple>

#include "core/error.hpp"
#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "host/conv2d.hpp"
#include "host/conv2d_winograd.hpp"
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
