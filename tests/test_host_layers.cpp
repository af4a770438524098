// CPU reference layers around the convolutions (host/maxpool2d, host/upsample_bilinear,
// host/pad_concat): hand-computed cases, edge cases (odd sizes, ties, NaN, one-pixel
// images), invariants, every backward against central finite differences in double, float
// against double, and shape errors.
#include <gtest/gtest.h>

#include <cmath>
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "core/rng.hpp"
#include "host/maxpool2d.hpp"
#include "host/pad_concat.hpp"
#include "host/upsample_bilinear.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using pillarseg::test::dot;
using pillarseg::test::numeric_gradient;
using pillarseg::test::random_tensor;
using namespace pillarseg::host;

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

// Distinct values at least 0.01 apart in random order: no window of maxpool has two values
// within a finite-difference step of each other, so the argmax cannot change under it.
TensorD distinct_tensor(const Shape& shape, Rng& rng) {
  TensorD t(shape);
  std::vector<double> values(static_cast<size_t>(t.numel()));
  for (size_t i = 0; i < values.size(); ++i) values[i] = 0.01 * static_cast<double>(i) - 1.0;
  rng.shuffle(values.begin(), values.end());
  for (int64_t i = 0; i < t.numel(); ++i) t[i] = values[static_cast<size_t>(i)];
  return t;
}

TensorD filled(const Shape& shape, std::vector<double> values) {
  TensorD t(shape);
  EXPECT_EQ(static_cast<int64_t>(values.size()), t.numel());
  for (int64_t i = 0; i < t.numel(); ++i) t[i] = values[static_cast<size_t>(i)];
  return t;
}

double sum(const TensorD& t) {
  double s = 0;
  for (int64_t i = 0; i < t.numel(); ++i) s += t[i];
  return s;
}

// These ops are linear (or piecewise linear away from their kinks), so central differences are
// exact up to rounding.
constexpr double kGradAtol = 1e-8;
constexpr double kGradRtol = 1e-6;

// A tensor of the wrong shape full of NaN: an op that accumulates into its output, or leaves
// part of it unwritten, shows NaN.
TensorD stale_output() {
  return TensorD({3, 1}, kNaN);
}

using StaleView = test::StaleView<double>;

// The odd image sizes every op is checked on, with B = 2 and C = 3.
const std::vector<Shape> kOddShapes = {{2, 3, 5, 7}, {2, 3, 3, 1}, {2, 3, 1, 1}, {2, 3, 4, 6}};

// ---- MaxPool2d ----

TEST(MaxPool2d, FloorsOddSizesAndIgnoresTheLastRowAndColumn) {
  // 5x5 plane with values 0..24, except the dropped last row and column hold 100.
  TensorD x({1, 1, 5, 5});
  for (int64_t i = 0; i < 25; ++i) x[i] = (i / 5 == 4 || i % 5 == 4) ? 100.0 : double(i);
  TensorD y = stale_output();
  Tensor<int32_t> argmax;
  maxpool2d_forward(x, y, &argmax);
  EXPECT_TRUE(test::all_close(y, filled({1, 1, 2, 2}, {6, 8, 16, 18}), 0, 0));
  EXPECT_EQ(argmax.shape(), (Shape{1, 1, 2, 2}));
  EXPECT_EQ(std::vector<int32_t>(argmax.data(), argmax.data() + 4),
            (std::vector<int32_t>{6, 8, 16, 18}));
}

TEST(MaxPool2d, TiesKeepTheFirstMaximumInRowMajorOrder) {
  // Windows: all equal; max at (0,1) and (1,0); max at (1,0) and (1,1); all -inf.
  const TensorD x = filled({1, 1, 2, 8}, {3, 3, 1, 5, 0, 0, -kInf, -kInf,  //
                                          3, 3, 5, 2, 4, 4, -kInf, -kInf});
  TensorD y;
  Tensor<int32_t> argmax;
  maxpool2d_forward(x, y, &argmax);
  EXPECT_TRUE(test::all_close(y, filled({1, 1, 1, 4}, {3, 5, 4, -kInf}), 0, 0));
  EXPECT_EQ(std::vector<int32_t>(argmax.data(), argmax.data() + 4),
            (std::vector<int32_t>{0, 3, 12, 6}));
}

TEST(MaxPool2d, NaNPropagatesWithTheLastNaNIndex) {
  // Window 0: a NaN among larger values; window 1: two NaNs (PyTorch keeps the last one);
  // window 2: no NaN.
  const TensorD x = filled({1, 1, 2, 6}, {5, 7, kNaN, 1, 2, 3,  //
                                          kNaN, 9, 0, kNaN, 4, 1});
  TensorD y;
  Tensor<int32_t> argmax;
  maxpool2d_forward(x, y, &argmax);
  EXPECT_TRUE(std::isnan(y[0]));
  EXPECT_TRUE(std::isnan(y[1]));
  EXPECT_EQ(y[2], 4.0);
  EXPECT_EQ(std::vector<int32_t>(argmax.data(), argmax.data() + 3),
            (std::vector<int32_t>{6, 9, 10}));
}

TEST(MaxPool2d, BackwardScattersToTheArgmaxOnly) {
  TensorD x({1, 1, 5, 5});
  for (int64_t i = 0; i < 25; ++i) x[i] = double(i);
  TensorD y;
  Tensor<int32_t> argmax;
  maxpool2d_forward(x, y, &argmax);
  TensorD dx = stale_output();
  maxpool2d_backward(filled({1, 1, 2, 2}, {1, 2, 3, 4}), argmax, x.shape(), dx);
  TensorD expected({1, 1, 5, 5});
  expected(0, 0, 1, 1) = 1;
  expected(0, 0, 1, 3) = 2;
  expected(0, 0, 3, 1) = 3;
  expected(0, 0, 3, 3) = 4;
  EXPECT_TRUE(test::all_close(dx, expected, 0, 0));
  StaleView in_arena(x.shape());  // row 4 and column 4 get no gradient: zero, not what was there
  maxpool2d_backward(filled({1, 1, 2, 2}, {1, 2, 3, 4}), argmax, x.shape(), in_arena.tensor);
  EXPECT_TRUE(test::all_close(in_arena.tensor, expected, 0, 0));
  StaleView pooled({1, 1, 2, 2});
  maxpool2d_forward(x, pooled.tensor, nullptr);
  EXPECT_TRUE(test::all_close(pooled.tensor, filled({1, 1, 2, 2}, {6, 8, 16, 18}), 0, 0));
}

TEST(MaxPool2d, BackwardMatchesFiniteDifferences) {
  for (const Shape& shape : kOddShapes) {
    SCOPED_TRACE(shape_str(shape));
    Rng rng(11);
    TensorD x = distinct_tensor(shape, rng);
    TensorD y;
    Tensor<int32_t> argmax;
    maxpool2d_forward(x, y, &argmax);
    const TensorD dy = random_tensor(y.shape(), rng);
    TensorD dx;
    maxpool2d_backward(dy, argmax, x.shape(), dx);
    const TensorD numeric = numeric_gradient(x, [&] {
      TensorD out;
      maxpool2d_forward(x, out, nullptr);
      return dot(dy, out);
    });
    EXPECT_TRUE(test::all_close(dx, numeric, kGradAtol, kGradRtol));

    TensorF yf, dxf;
    Tensor<int32_t> argmax_f;
    maxpool2d_forward(tensor_cast<float>(x), yf, &argmax_f);
    maxpool2d_backward(tensor_cast<float>(dy), argmax_f, x.shape(), dxf);
    EXPECT_TRUE(test::all_close(tensor_cast<double>(yf), y, 1e-7, 1e-7));
    EXPECT_TRUE(test::all_close(tensor_cast<double>(dxf), dx, 1e-7, 1e-7));
  }
}

TEST(MaxPool2d, ShapeErrorsNameTheProblem) {
  TensorD y;
  try {
    maxpool2d_forward(TensorD({3, 5, 5}), y, nullptr);
    FAIL() << "expected pillarseg::Error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("maxpool2d_forward"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("(3, 5, 5)"), std::string::npos) << e.what();
  }
  const TensorD x({1, 2, 5, 5});
  Tensor<int32_t> argmax;
  maxpool2d_forward(x, y, &argmax);
  TensorD dx;
  EXPECT_THROW(maxpool2d_backward(y, argmax, Shape{1, 2, 6, 6}, dx), Error);  // 3x3 != 2x2
  argmax[1] = 0;  // window (0, 1) covers columns 2-3: index 0 is outside it
  argmax[6] = 1;  // plane 1's window (1, 0) covers rows 2-3: index 1 is outside it
  try {
    maxpool2d_backward(y, argmax, x.shape(), dx);
    FAIL() << "expected pillarseg::Error";
  } catch (const Error& e) {  // the first bad element in the tensor's order, whatever the threads
    EXPECT_NE(std::string(e.what()).find("argmax element 1 = 0 is not in its 2x2 window at "
                                         "output (0, 1) of a 5x5 plane"),
              std::string::npos)
        << e.what();
  }
  argmax[1] = 2;  // right again: only plane 1's is left
  EXPECT_THROW(
      {
        try {
          maxpool2d_backward(y, argmax, x.shape(), dx);
        } catch (const Error& e) {
          EXPECT_NE(std::string(e.what()).find("argmax element 6 = 1 "), std::string::npos)
              << e.what();
          throw;
        }
      },
      Error);
}

// ---- Bilinear upsampling, align_corners = true ----

TEST(UpsampleBilinear, HandComputedTwoByTwo) {
  // Source coordinate d (2 - 1) / (4 - 1) = d / 3 on both axes; the input is the plane
  // 1 + x + 2 y, which bilinear interpolation reproduces exactly: y[i][j] = 1 + j / 3 + 2 i / 3.
  const TensorD x = filled({1, 1, 2, 2}, {1, 2, 3, 4});
  TensorD y = stale_output();
  upsample_bilinear_forward(x, y);
  ASSERT_EQ(y.shape(), (Shape{1, 1, 4, 4}));
  EXPECT_TRUE(test::all_close(y,
                              filled({1, 1, 4, 4}, {1, 4. / 3, 5. / 3, 2,        //
                                                    5. / 3, 2, 7. / 3, 8. / 3,   //
                                                    7. / 3, 8. / 3, 3, 10. / 3,  //
                                                    3, 10. / 3, 11. / 3, 4}),
                              1e-15, 1e-15));
}

TEST(UpsampleBilinear, HandComputedRowAndPixel) {
  // One row [0, 10, 20] -> 6 columns at 0, 0.4, 0.8, 1.2, 1.6, 2: [0, 4, 8, 12, 16, 20], and a
  // single input row is repeated (source row 0 for both output rows).
  TensorD y;
  upsample_bilinear_forward(filled({1, 1, 1, 3}, {0, 10, 20}), y);
  EXPECT_TRUE(test::all_close(y, filled({1, 1, 2, 6}, {0, 4, 8, 12, 16, 20, 0, 4, 8, 12, 16, 20}),
                              1e-14, 1e-14));
  upsample_bilinear_forward(filled({1, 1, 1, 1}, {7}), y);
  EXPECT_TRUE(test::all_close(y, TensorD({1, 1, 2, 2}, 7.0), 0, 0));
}

TEST(UpsampleBilinear, CornersAlignAndLinearRampsAreReproduced) {
  // x = a + b row + c col; output (oy, ox) samples it at row oy (H - 1) / (2H - 1), column
  // ox (W - 1) / (2W - 1), and the four corners coincide with the input's.
  const int64_t h = 5, w = 7;
  TensorD x({2, 3, h, w});
  for (int64_t p = 0; p < 6; ++p)
    for (int64_t r = 0; r < h; ++r)
      for (int64_t c = 0; c < w; ++c) x[(p * h + r) * w + c] = p - 0.5 * r + 0.25 * c;
  TensorD y;
  upsample_bilinear_forward(x, y);
  TensorD expected({2, 3, 2 * h, 2 * w});
  for (int64_t p = 0; p < 6; ++p)
    for (int64_t r = 0; r < 2 * h; ++r)
      for (int64_t c = 0; c < 2 * w; ++c) {
        const double row = double(r) * (h - 1) / (2 * h - 1);
        const double col = double(c) * (w - 1) / (2 * w - 1);
        expected[(p * 2 * h + r) * 2 * w + c] = p - 0.5 * row + 0.25 * col;
      }
  EXPECT_TRUE(test::all_close(y, expected, 1e-13, 1e-13));
  Rng rng(12);
  const TensorD noise = random_tensor({1, 1, h, w}, rng);
  upsample_bilinear_forward(noise, y);
  EXPECT_EQ(y(0, 0, 0, 0), noise(0, 0, 0, 0));
  EXPECT_EQ(y(0, 0, 0, 2 * w - 1), noise(0, 0, 0, w - 1));
  EXPECT_EQ(y(0, 0, 2 * h - 1, 0), noise(0, 0, h - 1, 0));
  EXPECT_EQ(y(0, 0, 2 * h - 1, 2 * w - 1), noise(0, 0, h - 1, w - 1));
}

TEST(UpsampleBilinear, BackwardMatchesFiniteDifferencesAndConservesTheSum) {
  for (const Shape& shape : kOddShapes) {
    SCOPED_TRACE(shape_str(shape));
    Rng rng(13);
    TensorD x = random_tensor(shape, rng);
    const TensorD dy = random_tensor({shape[0], shape[1], 2 * shape[2], 2 * shape[3]}, rng);
    TensorD dx = stale_output();
    upsample_bilinear_backward(dy, dx);
    const TensorD numeric = numeric_gradient(x, [&] {
      TensorD out;
      upsample_bilinear_forward(x, out);
      return dot(dy, out);
    });
    EXPECT_TRUE(test::all_close(dx, numeric, kGradAtol, kGradRtol));
    StaleView in_arena(shape), y_in_arena(dy.shape());
    upsample_bilinear_backward(dy, in_arena.tensor);
    EXPECT_TRUE(test::all_close(in_arena.tensor, dx, 0, 0));
    // Each output's weights sum to 1, so the backward moves all of the gradient.
    EXPECT_NEAR(sum(dx), sum(dy), 1e-12);

    TensorF yf, dxf;
    TensorD y;
    upsample_bilinear_forward(x, y);
    upsample_bilinear_forward(x, y_in_arena.tensor);
    EXPECT_TRUE(test::all_close(y_in_arena.tensor, y, 0, 0));
    upsample_bilinear_forward(tensor_cast<float>(x), yf);
    upsample_bilinear_backward(tensor_cast<float>(dy), dxf);
    EXPECT_TRUE(test::all_close(tensor_cast<double>(yf), y, 1e-6, 1e-6));
    EXPECT_TRUE(test::all_close(tensor_cast<double>(dxf), dx, 1e-6, 1e-6));
  }
}

TEST(UpsampleBilinear, ShapeErrorsNameTheProblem) {
  TensorD y;
  try {
    upsample_bilinear_forward(TensorD({1, 2, 0, 3}), y);
    FAIL() << "expected pillarseg::Error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("upsample_bilinear_forward"), std::string::npos)
        << e.what();
    EXPECT_NE(std::string(e.what()).find("(1, 2, 0, 3)"), std::string::npos) << e.what();
  }
  TensorD dx;
  EXPECT_THROW(upsample_bilinear_backward(TensorD({1, 2, 4, 5}), dx), Error);  // odd width
}

// ---- Pad + concatenate (U-Net Up join) ----

// Checks y = [skip, up placed at (top, left)] with zeros elsewhere in the up channels.
void expect_padded_concat(const TensorD& skip, const TensorD& up, const TensorD& y, int64_t top,
                          int64_t left) {
  const int64_t cs = skip.dim(1), cu = up.dim(1), h = skip.dim(2), w = skip.dim(3);
  ASSERT_EQ(y.shape(), (Shape{skip.dim(0), cs + cu, h, w}));
  for (int64_t b = 0; b < skip.dim(0); ++b)
    for (int64_t c = 0; c < cs + cu; ++c)
      for (int64_t r = 0; r < h; ++r)
        for (int64_t col = 0; col < w; ++col) {
          double expected = 0;
          if (c < cs) {
            expected = skip(b, c, r, col);
          } else if (r >= top && r < top + up.dim(2) && col >= left && col < left + up.dim(3)) {
            expected = up(b, c - cs, r - top, col - left);
          }
          ASSERT_EQ(y(b, c, r, col), expected)
              << "b " << b << " c " << c << " row " << r << " col " << col;
        }
}

TEST(PadConcat, OddDifferencePutsTheExtraZeroRowAndColumnAfter) {
  // diff = 1 on both axes: pad [0, 1], so up sits at rows 0-5, columns 0-3 of the 7x5 skip.
  Rng rng(14);
  const TensorD skip = random_tensor({2, 2, 7, 5}, rng);
  const TensorD up = random_tensor({2, 3, 6, 4}, rng);
  TensorD y = stale_output();
  pad_concat_forward(skip, up, y);
  expect_padded_concat(skip, up, y, 0, 0);
  for (int64_t b = 0; b < 2; ++b)
    for (int64_t c = 2; c < 5; ++c) {
      for (int64_t col = 0; col < 5; ++col) EXPECT_EQ(y(b, c, 6, col), 0.0);
      for (int64_t r = 0; r < 7; ++r) EXPECT_EQ(y(b, c, r, 4), 0.0);
    }
  StaleView in_arena({2, 5, 7, 5});  // the padding is written zero, not left as it was
  pad_concat_forward(skip, up, in_arena.tensor);
  expect_padded_concat(skip, up, in_arena.tensor, 0, 0);
}

TEST(PadConcat, LargerDifferencesSplitAsPyTorchPads) {
  // diff 3 rows -> [1, 2], diff 4 columns -> [2, 2]; equal sizes -> plain concatenation.
  Rng rng(15);
  const TensorD skip = random_tensor({1, 3, 9, 8}, rng);
  const TensorD up = random_tensor({1, 1, 6, 4}, rng);
  TensorD y;
  pad_concat_forward(skip, up, y);
  expect_padded_concat(skip, up, y, 1, 2);
  const TensorD same = random_tensor({1, 2, 9, 8}, rng);
  pad_concat_forward(skip, same, y);
  expect_padded_concat(skip, same, y, 0, 0);
}

TEST(PadConcat, BackwardMatchesFiniteDifferences) {
  const std::vector<std::pair<Shape, Shape>> cases = {{{2, 3, 7, 5}, {2, 5, 6, 4}},
                                                      {{2, 1, 5, 7}, {2, 3, 2, 3}},
                                                      {{2, 3, 3, 1}, {2, 3, 1, 1}},
                                                      {{2, 3, 1, 1}, {2, 1, 1, 1}}};
  for (const auto& [skip_shape, up_shape] : cases) {
    SCOPED_TRACE(shape_str(skip_shape) + " " + shape_str(up_shape));
    Rng rng(16);
    TensorD skip = random_tensor(skip_shape, rng);
    TensorD up = random_tensor(up_shape, rng);
    const TensorD dy = random_tensor(
        {skip_shape[0], skip_shape[1] + up_shape[1], skip_shape[2], skip_shape[3]}, rng);
    const auto loss = [&] {
      TensorD out;
      pad_concat_forward(skip, up, out);
      return dot(dy, out);
    };
    TensorD d_skip = stale_output(), d_up = stale_output();
    pad_concat_backward(dy, skip_shape, up_shape, &d_skip, &d_up);
    EXPECT_TRUE(test::all_close(d_skip, numeric_gradient(skip, loss), kGradAtol, kGradRtol));
    EXPECT_TRUE(test::all_close(d_up, numeric_gradient(up, loss), kGradAtol, kGradRtol));
    StaleView skip_in_arena(skip_shape), up_in_arena(up_shape);
    pad_concat_backward(dy, skip_shape, up_shape, &skip_in_arena.tensor, &up_in_arena.tensor);
    EXPECT_TRUE(test::all_close(skip_in_arena.tensor, d_skip, 0, 0));
    EXPECT_TRUE(test::all_close(up_in_arena.tensor, d_up, 0, 0));

    // Either output alone, and float against double (pure copies: exact).
    TensorD d_up_only;
    pad_concat_backward(dy, skip_shape, up_shape, nullptr, &d_up_only);
    EXPECT_TRUE(test::all_close(d_up_only, d_up, 0, 0));
    TensorF d_skip_f, d_up_f;
    pad_concat_backward(tensor_cast<float>(dy), skip_shape, up_shape, &d_skip_f, &d_up_f);
    EXPECT_TRUE(test::all_close(d_skip_f, tensor_cast<float>(d_skip), 0, 0));
    EXPECT_TRUE(test::all_close(d_up_f, tensor_cast<float>(d_up), 0, 0));
  }
}

TEST(PadConcat, ShapeErrorsNameTheProblem) {
  TensorD y;
  try {
    pad_concat_forward(TensorD({1, 2, 6, 4}), TensorD({1, 2, 7, 4}), y);  // up taller than skip
    FAIL() << "expected pillarseg::Error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("pad_concat_forward"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("(1, 2, 7, 4)"), std::string::npos) << e.what();
  }
  EXPECT_THROW(pad_concat_forward(TensorD({2, 2, 6, 4}), TensorD({1, 2, 6, 4}), y), Error);
  TensorD d_skip;
  EXPECT_THROW(pad_concat_backward(TensorD({1, 3, 6, 4}), Shape{1, 2, 6, 4}, Shape{1, 2, 6, 4},
                                   &d_skip, nullptr),
               Error);  // dy has 3 channels, skip + up have 4
}

// ---- ReLU ----

}  // namespace
