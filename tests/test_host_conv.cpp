// CPU reference convolutions (host/conv2d, host/conv_transpose2d): forward against direct loops
// written from the PyTorch definitions, hand-computed cases, every backward against central
// finite differences in double, float against double, determinism across thread counts,
// overwrite (not accumulate) semantics and shape errors.
#include <gtest/gtest.h>

#include <cmath>
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "host/conv2d.hpp"
#include "host/conv_transpose2d.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using pillarseg::test::dot;
using pillarseg::test::numeric_gradient;
using pillarseg::test::random_tensor;
using namespace pillarseg::host;

namespace {

// The convolutions are linear in each argument, so central differences are exact up to
// rounding: about 1e-16 |loss| / eps ~ 1e-9 here.
constexpr double kGradAtol = 1e-8;
constexpr double kGradRtol = 1e-6;

// PyTorch's Conv2d definition, stride 1: y[b,o,oy,ox] = bias[o] + sum w[o,i,ky,kx] x[b,i,iy,ix],
// iy = oy + ky - pad, ix = ox + kx - pad, terms outside the image skipped.
template <class T>
Tensor<T> naive_conv2d(const Tensor<T>& x, const Tensor<T>& w, const Tensor<T>* bias, int pad) {
  const int64_t batch = x.dim(0), in_ch = x.dim(1), h = x.dim(2), wd = x.dim(3);
  const int64_t out_ch = w.dim(0), k = w.dim(2);
  const int64_t out_h = h + 2 * pad - k + 1, out_w = wd + 2 * pad - k + 1;
  Tensor<T> y({batch, out_ch, out_h, out_w});
  for (int64_t b = 0; b < batch; ++b)
    for (int64_t o = 0; o < out_ch; ++o)
      for (int64_t oy = 0; oy < out_h; ++oy)
        for (int64_t ox = 0; ox < out_w; ++ox) {
          double sum = bias != nullptr ? static_cast<double>((*bias)[o]) : 0.0;
          for (int64_t i = 0; i < in_ch; ++i)
            for (int64_t ky = 0; ky < k; ++ky)
              for (int64_t kx = 0; kx < k; ++kx) {
                const int64_t iy = oy + ky - pad, ix = ox + kx - pad;
                if (iy < 0 || iy >= h || ix < 0 || ix >= wd) continue;
                sum += static_cast<double>(w(o, i, ky, kx)) * static_cast<double>(x(b, i, iy, ix));
              }
          y(b, o, oy, ox) = static_cast<T>(sum);
        }
  return y;
}

// The adjoint of naive_conv2d by scattering: every term w x of y contributes dy w to dx and
// dy x to dw.
void naive_conv2d_backward(const TensorD& x, const TensorD& w, const TensorD& dy, int pad,
                           TensorD& dx, TensorD& dw, TensorD& db) {
  const int64_t in_ch = x.dim(1), h = x.dim(2), wd = x.dim(3), k = w.dim(2);
  dx = TensorD(x.shape());
  dw = TensorD(w.shape());
  db = TensorD({w.dim(0)});
  for (int64_t b = 0; b < dy.dim(0); ++b)
    for (int64_t o = 0; o < dy.dim(1); ++o)
      for (int64_t oy = 0; oy < dy.dim(2); ++oy)
        for (int64_t ox = 0; ox < dy.dim(3); ++ox) {
          const double g = dy(b, o, oy, ox);
          db[o] += g;
          for (int64_t i = 0; i < in_ch; ++i)
            for (int64_t ky = 0; ky < k; ++ky)
              for (int64_t kx = 0; kx < k; ++kx) {
                const int64_t iy = oy + ky - pad, ix = ox + kx - pad;
                if (iy < 0 || iy >= h || ix < 0 || ix >= wd) continue;
                dx(b, i, iy, ix) += g * w(o, i, ky, kx);
                dw(o, i, ky, kx) += g * x(b, i, iy, ix);
              }
        }
}

// PyTorch's ConvTranspose2d definition (scatter form), stride 2, kernel 2:
// y[b, o, 2 h + ky, 2 w + kx] += x[b, i, h, w] w[i, o, ky, kx], plus bias[o].
TensorD naive_conv_transpose2d(const TensorD& x, const TensorD& w, const TensorD* bias) {
  const int64_t batch = x.dim(0), in_ch = x.dim(1), h = x.dim(2), wd = x.dim(3);
  const int64_t out_ch = w.dim(1);
  TensorD y({batch, out_ch, 2 * h, 2 * wd});
  for (int64_t b = 0; b < batch; ++b)
    for (int64_t o = 0; o < out_ch; ++o)
      for (int64_t oy = 0; oy < 2 * h; ++oy)
        for (int64_t ox = 0; ox < 2 * wd; ++ox) y(b, o, oy, ox) = bias ? (*bias)[o] : 0.0;
  for (int64_t b = 0; b < batch; ++b)
    for (int64_t i = 0; i < in_ch; ++i)
      for (int64_t iy = 0; iy < h; ++iy)
        for (int64_t ix = 0; ix < wd; ++ix)
          for (int64_t o = 0; o < out_ch; ++o)
            for (int64_t ky = 0; ky < 2; ++ky)
              for (int64_t kx = 0; kx < 2; ++kx)
                y(b, o, 2 * iy + ky, 2 * ix + kx) += x(b, i, iy, ix) * w(i, o, ky, kx);
  return y;
}

TensorD filled(const Shape& shape, std::vector<double> values) {
  TensorD t(shape);
  EXPECT_EQ(static_cast<int64_t>(values.size()), t.numel());
  for (int64_t i = 0; i < t.numel(); ++i) t[i] = values[static_cast<size_t>(i)];
  return t;
}

// A tensor of the wrong shape full of NaN: an op that accumulates into its output, or leaves
// part of it unwritten, shows NaN.
template <class T>
Tensor<T> stale_output() {
  return Tensor<T>({3, 1}, std::numeric_limits<T>::quiet_NaN());
}

struct ConvCase {
  int64_t batch, in_ch, out_ch, height, width, kernel;
  int pad;
  bool bias;
  std::string name() const {
    return "B" + std::to_string(batch) + "_I" + std::to_string(in_ch) + "_O" +
           std::to_string(out_ch) + "_" + std::to_string(height) + "x" + std::to_string(width) +
           "_k" + std::to_string(kernel) + "_pad" + std::to_string(pad) + (bias ? "_bias" : "");
  }
};

class Conv2dCases : public ::testing::TestWithParam<ConvCase> {};

TEST_P(Conv2dCases, ForwardMatchesDirectLoops) {
  const ConvCase c = GetParam();
  Rng rng(1);
  const TensorD x = random_tensor({c.batch, c.in_ch, c.height, c.width}, rng);
  const TensorD w = random_tensor({c.out_ch, c.in_ch, c.kernel, c.kernel}, rng);
  const TensorD b = random_tensor({c.out_ch}, rng);
  const TensorD* bias = c.bias ? &b : nullptr;
  TensorD y = stale_output<double>();
  conv2d_forward(x, w, bias, c.pad, y);
  EXPECT_TRUE(test::all_close(y, naive_conv2d(x, w, bias, c.pad), 1e-13, 1e-12));

  // float against double: the same data in float agrees to float rounding.
  const TensorF bf = tensor_cast<float>(b);
  TensorF yf;
  conv2d_forward(tensor_cast<float>(x), tensor_cast<float>(w), c.bias ? &bf : nullptr, c.pad, yf);
  EXPECT_TRUE(test::all_close(tensor_cast<double>(yf), y, 1e-5, 1e-5));
}

TEST_P(Conv2dCases, BackwardMatchesFiniteDifferences) {
  const ConvCase c = GetParam();
  Rng rng(2);
  TensorD x = random_tensor({c.batch, c.in_ch, c.height, c.width}, rng);
  TensorD w = random_tensor({c.out_ch, c.in_ch, c.kernel, c.kernel}, rng);
  TensorD b = random_tensor({c.out_ch}, rng);
  TensorD* bias = c.bias ? &b : nullptr;
  TensorD y;
  conv2d_forward(x, w, bias, c.pad, y);
  const TensorD dy = random_tensor(y.shape(), rng);  // loss = <dy, y>
  const auto loss = [&] {
    TensorD out;
    conv2d_forward(x, w, bias, c.pad, out);
    return dot(dy, out);
  };

  TensorD dx = stale_output<double>(), dw = stale_output<double>(), db = stale_output<double>();
  conv2d_backward(x, w, dy, c.pad, &dx, &dw, &db);
  EXPECT_TRUE(test::all_close(dx, numeric_gradient(x, loss), kGradAtol, kGradRtol)) << "dx";
  EXPECT_TRUE(test::all_close(dw, numeric_gradient(w, loss), kGradAtol, kGradRtol)) << "dw";
  if (c.bias) {
    EXPECT_TRUE(test::all_close(db, numeric_gradient(b, loss), kGradAtol, kGradRtol)) << "db";
  }

  // float against double.
  TensorF dxf, dwf, dbf;
  conv2d_backward(tensor_cast<float>(x), tensor_cast<float>(w), tensor_cast<float>(dy), c.pad, &dxf,
                  &dwf, &dbf);
  EXPECT_TRUE(test::all_close(tensor_cast<double>(dxf), dx, 1e-5, 1e-5));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(dwf), dw, 1e-5, 1e-5));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(dbf), db, 1e-5, 1e-5));
}

INSTANTIATE_TEST_SUITE_P(
    OddSizes, Conv2dCases,
    ::testing::Values(ConvCase{2, 3, 5, 5, 7, 3, 1, true},    // the U-Net's 3x3 "same" conv
                      ConvCase{2, 3, 5, 3, 1, 3, 1, true},    // a one-column image
                      ConvCase{2, 3, 5, 1, 1, 3, 1, false},   // one pixel: only the centre tap
                      ConvCase{2, 3, 5, 5, 7, 1, 0, true},    // the 1x1 head
                      ConvCase{1, 2, 3, 6, 5, 5, 2, true},    // larger odd kernel
                      ConvCase{2, 3, 4, 5, 7, 3, 0, true},    // no padding: output 3x5
                      ConvCase{1, 2, 3, 3, 4, 3, 2, true},    // pad > k / 2: output 5x6
                      ConvCase{1, 2, 2, 2, 3, 1, 2, true},    // pad > k - 1: border of bias
                      ConvCase{1, 2, 3, 4, 5, 2, 1, false}),  // even kernel
    [](const ::testing::TestParamInfo<ConvCase>& param_info) { return param_info.param.name(); });

TEST(Conv2d, HandComputedAllOnesKernel) {
  // 3x3 image 1..9, all-ones 3x3 kernel, pad 1: each output is the sum of its 3x3 neighbourhood.
  const TensorD x = filled({1, 1, 3, 3}, {1, 2, 3, 4, 5, 6, 7, 8, 9});
  const TensorD w({1, 1, 3, 3}, 1.0);
  const TensorD bias({1}, 0.5);
  TensorD y;
  conv2d_forward(x, w, &bias, 1, y);
  const TensorD expected =
      filled({1, 1, 3, 3}, {12.5, 21.5, 16.5, 27.5, 45.5, 33.5, 24.5, 39.5, 28.5});
  EXPECT_TRUE(test::all_close(y, expected, 0, 0));
}

TEST(Conv2d, HandComputedPointwiseMixesChannels) {
  // 1x1 kernel: y[o] = sum_i w[o, i] x[i] per pixel.
  const TensorD x = filled({1, 2, 1, 2}, {1, 2, 10, 20});  // channel 0: [1 2], channel 1: [10 20]
  const TensorD w = filled({2, 2, 1, 1}, {1, 1, 2, -1});
  TensorD y;
  conv2d_forward(x, w, nullptr, 0, y);
  EXPECT_TRUE(test::all_close(y, filled({1, 2, 1, 2}, {11, 22, -8, -16}), 0, 0));
}

// Shapes that split into several im2col tiles (forward and dx) and several input-channel blocks
// of the weight gradient, each tile boundary inside an image.
TEST(Conv2d, LargeTiledShapesMatchDirectLoops) {
  for (const ConvCase c :
       {ConvCase{2, 64, 5, 61, 150, 3, 1, true}, ConvCase{1, 300, 4, 101, 40, 1, 0, true}}) {
    SCOPED_TRACE(c.name());
    Rng rng(3);
    const TensorD x = random_tensor({c.batch, c.in_ch, c.height, c.width}, rng);
    const TensorD w = random_tensor({c.out_ch, c.in_ch, c.kernel, c.kernel}, rng);
    const TensorD b = random_tensor({c.out_ch}, rng);
    TensorD y;
    conv2d_forward(x, w, &b, c.pad, y);
    EXPECT_TRUE(test::all_close(y, naive_conv2d(x, w, &b, c.pad), 1e-12, 1e-12));

    const TensorD dy = random_tensor(y.shape(), rng);
    TensorD dx, dw, db, naive_dx, naive_dw, naive_db;
    conv2d_backward(x, w, dy, c.pad, &dx, &dw, &db);
    naive_conv2d_backward(x, w, dy, c.pad, naive_dx, naive_dw, naive_db);
    EXPECT_TRUE(test::all_close(dx, naive_dx, 1e-12, 1e-12));
    EXPECT_TRUE(test::all_close(dw, naive_dw, 1e-10, 1e-12));
    EXPECT_TRUE(test::all_close(db, naive_db, 1e-10, 1e-12));

    TensorF yf, dxf, dwf, dbf;
    const TensorF xf = tensor_cast<float>(x), wf = tensor_cast<float>(w);
    const TensorF bf = tensor_cast<float>(b), dyf = tensor_cast<float>(dy);
    conv2d_forward(xf, wf, &bf, c.pad, yf);
    conv2d_backward(xf, wf, dyf, c.pad, &dxf, &dwf, &dbf);
    EXPECT_TRUE(test::all_close(tensor_cast<double>(yf), y, 1e-4, 1e-4));
    EXPECT_TRUE(test::all_close(tensor_cast<double>(dxf), dx, 1e-4, 1e-4));
    // dw and db sum ~20000 products each: float rounding grows with the sum's length.
    EXPECT_TRUE(test::all_close(tensor_cast<double>(dwf), dw, 1e-2, 1e-4));
    EXPECT_TRUE(test::all_close(tensor_cast<double>(dbf), db, 1e-2, 1e-4));
  }
}

TEST(Conv2d, SameResultsWithOneOrTwoThreads) {
  Rng rng(4);
  const TensorF x = tensor_cast<float>(random_tensor({2, 48, 61, 90}, rng));
  const TensorF w = tensor_cast<float>(random_tensor({16, 48, 3, 3}, rng));
  const TensorF b = tensor_cast<float>(random_tensor({16}, rng));
  const TensorF dy = tensor_cast<float>(random_tensor({2, 16, 61, 90}, rng));
  TensorF y[2], dx[2], dw[2], db[2];
  for (int run = 0; run < 2; ++run) {
    set_num_threads(run + 1);
    conv2d_forward(x, w, &b, 1, y[run]);
    conv2d_backward(x, w, dy, 1, &dx[run], &dw[run], &db[run]);
  }
  set_num_threads(0);
  EXPECT_TRUE(test::all_close(y[1], y[0], 0, 0));
  EXPECT_TRUE(test::all_close(dx[1], dx[0], 0, 0));
  EXPECT_TRUE(test::all_close(dw[1], dw[0], 0, 0));
  EXPECT_TRUE(test::all_close(db[1], db[0], 0, 0));
}

TEST(Conv2d, BackwardComputesOnlyTheGradientsAskedFor) {
  Rng rng(5);
  const TensorD x = random_tensor({2, 3, 5, 7}, rng);
  const TensorD w = random_tensor({4, 3, 3, 3}, rng);
  const TensorD dy = random_tensor({2, 4, 5, 7}, rng);
  TensorD dx_all, dw_all, db_all, dx_only, dw_only;
  conv2d_backward(x, w, dy, 1, &dx_all, &dw_all, &db_all);
  conv2d_backward(x, w, dy, 1, &dx_only, nullptr, nullptr);
  conv2d_backward(x, w, dy, 1, nullptr, &dw_only, nullptr);
  EXPECT_TRUE(test::all_close(dx_only, dx_all, 0, 0));
  EXPECT_TRUE(test::all_close(dw_only, dw_all, 0, 0));
}

TEST(Conv2d, EmptyBatchGivesEmptyOutputAndZeroWeightGradient) {
  const TensorD x({0, 3, 5, 7});
  const TensorD w({4, 3, 3, 3}, 1.0);
  TensorD y, dw = stale_output<double>(), db = stale_output<double>();
  conv2d_forward(x, w, nullptr, 1, y);
  EXPECT_EQ(y.shape(), (Shape{0, 4, 5, 7}));
  conv2d_backward(x, w, y, 1, nullptr, &dw, &db);
  EXPECT_TRUE(test::all_close(dw, TensorD(w.shape()), 0, 0));
  EXPECT_TRUE(test::all_close(db, TensorD({4}), 0, 0));
}

TEST(Conv2d, ShapeErrorsNameTheProblem) {
  const TensorD x({1, 3, 5, 7});
  const TensorD w({4, 2, 3, 3});  // expects 2 input channels, x has 3
  TensorD y;
  try {
    conv2d_forward(x, w, nullptr, 1, y);
    FAIL() << "expected pillarseg::Error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("conv2d_forward"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("I = 2"), std::string::npos) << e.what();
  }
  const TensorD w_ok({4, 3, 3, 3});
  const TensorD bad_bias({3});
  EXPECT_THROW(conv2d_forward(x, w_ok, &bad_bias, 1, y), Error);
  EXPECT_THROW(conv2d_forward(x, w_ok, nullptr, -1, y), Error);
  EXPECT_THROW(conv2d_forward(TensorD({1, 3, 1, 1}), w_ok, nullptr, 0, y), Error);  // 3x3 on 1x1
  EXPECT_THROW(conv2d_forward(x, TensorD({4, 3, 3, 2}), nullptr, 1, y), Error);     // not square
  TensorD dx;
  EXPECT_THROW(conv2d_backward(x, w_ok, TensorD({1, 4, 5, 6}), 1, &dx, nullptr, nullptr), Error);
}

TEST(ConvTranspose2d, HandComputed) {
  // Each input pixel pastes x * w into its own 2x2 output block.
  const TensorD x = filled({1, 1, 1, 2}, {1, 2});
  const TensorD w = filled({1, 1, 2, 2}, {1, 2, 3, 4});
  const TensorD bias({1}, 0.5);
  TensorD y;
  conv_transpose2d_forward(x, w, &bias, y);
  EXPECT_TRUE(
      test::all_close(y, filled({1, 1, 2, 4}, {1.5, 2.5, 2.5, 4.5, 3.5, 4.5, 6.5, 8.5}), 0, 0));
}

struct TransposeCase {
  int64_t batch, in_ch, out_ch, height, width;
  bool bias;
};

class ConvTranspose2dCases : public ::testing::TestWithParam<TransposeCase> {};

TEST_P(ConvTranspose2dCases, ForwardMatchesDirectLoops) {
  const TransposeCase c = GetParam();
  Rng rng(6);
  const TensorD x = random_tensor({c.batch, c.in_ch, c.height, c.width}, rng);
  const TensorD w = random_tensor({c.in_ch, c.out_ch, 2, 2}, rng);
  const TensorD b = random_tensor({c.out_ch}, rng);
  const TensorD* bias = c.bias ? &b : nullptr;
  TensorD y = stale_output<double>();
  conv_transpose2d_forward(x, w, bias, y);
  EXPECT_TRUE(test::all_close(y, naive_conv_transpose2d(x, w, bias), 1e-13, 1e-12));

  const TensorF bf = tensor_cast<float>(b);
  TensorF yf;
  conv_transpose2d_forward(tensor_cast<float>(x), tensor_cast<float>(w), c.bias ? &bf : nullptr,
                           yf);
  EXPECT_TRUE(test::all_close(tensor_cast<double>(yf), y, 1e-5, 1e-5));
}

TEST_P(ConvTranspose2dCases, BackwardMatchesFiniteDifferences) {
  const TransposeCase c = GetParam();
  Rng rng(7);
  TensorD x = random_tensor({c.batch, c.in_ch, c.height, c.width}, rng);
  TensorD w = random_tensor({c.in_ch, c.out_ch, 2, 2}, rng);
  TensorD b = random_tensor({c.out_ch}, rng);
  TensorD* bias = c.bias ? &b : nullptr;
  const TensorD dy = random_tensor({c.batch, c.out_ch, 2 * c.height, 2 * c.width}, rng);
  const auto loss = [&] {
    TensorD out;
    conv_transpose2d_forward(x, w, bias, out);
    return dot(dy, out);
  };

  TensorD dx = stale_output<double>(), dw = stale_output<double>(), db = stale_output<double>();
  conv_transpose2d_backward(x, w, dy, &dx, &dw, &db);
  EXPECT_TRUE(test::all_close(dx, numeric_gradient(x, loss), kGradAtol, kGradRtol)) << "dx";
  EXPECT_TRUE(test::all_close(dw, numeric_gradient(w, loss), kGradAtol, kGradRtol)) << "dw";
  if (c.bias) {
    EXPECT_TRUE(test::all_close(db, numeric_gradient(b, loss), kGradAtol, kGradRtol)) << "db";
  }

  TensorF dxf, dwf, dbf;
  conv_transpose2d_backward(tensor_cast<float>(x), tensor_cast<float>(w), tensor_cast<float>(dy),
                            &dxf, &dwf, &dbf);
  EXPECT_TRUE(test::all_close(tensor_cast<double>(dxf), dx, 1e-5, 1e-5));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(dwf), dw, 1e-5, 1e-5));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(dbf), db, 1e-5, 1e-5));
}

// The dy-consuming backward rearranges dy in place; its gradients are the copying backward's,
// bit for bit (the same products in the same order).
TEST_P(ConvTranspose2dCases, BackwardOverwritingDyIsBitIdentical) {
  const TransposeCase c = GetParam();
  Rng rng(11);
  const TensorF x = tensor_cast<float>(random_tensor({c.batch, c.in_ch, c.height, c.width}, rng));
  const TensorF w = tensor_cast<float>(random_tensor({c.in_ch, c.out_ch, 2, 2}, rng));
  const TensorF dy =
      tensor_cast<float>(random_tensor({c.batch, c.out_ch, 2 * c.height, 2 * c.width}, rng));
  TensorF dx, dw, db;
  conv_transpose2d_backward(x, w, dy, &dx, &dw, &db);
  TensorF scratch = dy, dx2 = stale_output<float>(), dw2 = stale_output<float>(),
          db2 = stale_output<float>();
  conv_transpose2d_backward_overwriting_dy(x, w, scratch, &dx2, &dw2, &db2);
  EXPECT_TRUE(test::all_close(dx2, dx, 0, 0)) << "dx";
  EXPECT_TRUE(test::all_close(dw2, dw, 0, 0)) << "dw";
  EXPECT_TRUE(test::all_close(db2, db, 0, 0)) << "db";
}

INSTANTIATE_TEST_SUITE_P(OddSizes, ConvTranspose2dCases,
                         ::testing::Values(TransposeCase{2, 3, 5, 5, 7, true},
                                           TransposeCase{2, 3, 5, 3, 1, true},
                                           TransposeCase{2, 5, 3, 1, 1, false},
                                           TransposeCase{1, 1, 1, 2, 3, true}));

TEST(ConvTranspose2d, ShapeErrorsNameTheProblem) {
  const TensorD x({1, 3, 5, 7});
  const TensorD w({4, 2, 2, 2});  // (I, O, 2, 2) with I = 4, x has 3 channels
  TensorD y;
  try {
    conv_transpose2d_forward(x, w, nullptr, y);
    FAIL() << "expected pillarseg::Error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("conv_transpose2d_forward"), std::string::npos)
        << e.what();
    EXPECT_NE(std::string(e.what()).find("I = 4"), std::string::npos) << e.what();
  }
  EXPECT_THROW(conv_transpose2d_forward(x, TensorD({3, 2, 3, 3}), nullptr, y), Error);
  TensorD dx;
  EXPECT_THROW(conv_transpose2d_backward(x, TensorD({3, 2, 2, 2}), TensorD({1, 2, 10, 13}), &dx,
                                         nullptr, nullptr),
               Error);
}

}  // namespace
