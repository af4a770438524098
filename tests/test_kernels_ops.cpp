// The non-convolution kernels besides BatchNorm and the PFN, on the CUDA emulation, against the
// CPU reference ops of host/ on the same inputs: scatter/gather into a channel band
// (kernels/scatter.cu), max pooling (maxpool2d.cu), bilinear upsampling (upsample_bilinear.cu),
// pad + concat (pad_concat.cu), the elementwise ops and band copies (elementwise.cu), softmax and
// arg-max (softmax.cu), the two losses (losses.cu) and the AdamW step (adam.cu). Cases: sizes
// that are not multiples of the tile or block, odd planes, 1 x 1 planes, 0 and 1 pillar, B = 2,
// misaligned arrays, NaN and Inf where they matter (max pooling, softmax, arg-max, unlabeled
// cells of the losses), guard words after every output, determinism, argument checks. Data
// movement and max/arg-max must match bit for bit; arithmetic within atol + rtol |ref|.
#include <gtest/gtest.h>
#include <omp.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "host/adam.hpp"
#include "host/losses.hpp"
#include "host/maxpool2d.hpp"
#include "host/mirror_add.hpp"
#include "host/pad_concat.hpp"
#include "host/scatter.hpp"
#include "host/softmax.hpp"
#include "host/upsample_bilinear.hpp"
#include "kernels/adam.cuh"
#include "kernels/elementwise.cuh"
#include "kernels/losses.cuh"
#include "kernels/maxpool2d.cuh"
#include "kernels/mirror_add.cuh"
#include "kernels/pad_concat.cuh"
#include "kernels/scatter.cuh"
#include "kernels/softmax.cuh"
#include "kernels/upsample_bilinear.cuh"
#include "tests/kernel_test_helpers.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using kernel_test::error_message;
using kernel_test::GuardedArray;
using kernel_test::normal_tensor;
using kernel_test::normal_values;
using kernel_test::same_bits;

namespace {

constexpr float kNan = std::numeric_limits<float>::quiet_NaN();
constexpr float kInf = std::numeric_limits<float>::infinity();

::testing::AssertionResult close(const std::vector<float>& actual, const Tensor<float>& expected,
                                 double atol, double rtol) {
  if (static_cast<std::int64_t>(actual.size()) != expected.numel()) {
    return ::testing::AssertionFailure()
           << "size " << actual.size() << " != expected " << expected.numel();
  }
  return test::all_close(actual.data(), expected.data(), expected.numel(), atol, rtol);
}

// `count` distinct cells (b, iy, ix) of a (batch, height, width) canvas as (P, 3) int32 rows, in
// a seeded random order.
Tensor<std::int32_t> unique_cells(std::int64_t count, std::int64_t batch, std::int64_t height,
                                  std::int64_t width, std::uint64_t seed) {
  std::vector<std::int64_t> all(static_cast<std::size_t>(batch * height * width));
  for (std::size_t i = 0; i < all.size(); ++i) all[i] = static_cast<std::int64_t>(i);
  Rng rng(seed);
  Tensor<std::int32_t> cells({count, 3});
  for (std::int64_t p = 0; p < count; ++p) {
    const auto pick =
        p + static_cast<std::int64_t>(rng.uniform_int(static_cast<std::uint64_t>(all.size()) - p));
    std::swap(all[static_cast<std::size_t>(p)], all[static_cast<std::size_t>(pick)]);
    const std::int64_t cell = all[static_cast<std::size_t>(p)];
    cells(p, 0) = static_cast<std::int32_t>(cell / (height * width));
    cells(p, 1) = static_cast<std::int32_t>(cell / width % height);
    cells(p, 2) = static_cast<std::int32_t>(cell % width);
  }
  return cells;
}

std::vector<std::int32_t> to_vector(const Tensor<std::int32_t>& t) {
  return std::vector<std::int32_t>(t.begin(), t.end());
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Scatter

namespace {

struct ScatterCase {
  std::int64_t batch, canvas_channels, height, width, channel0, channels, pillars;
};

const std::vector<ScatterCase> kScatterCases = {
    {2, 5, 7, 9, 2, 3, 40},    // a band in the middle of the canvas, B = 2
    {1, 4, 6, 5, 0, 4, 30},    // the canvas is all band (one memset)
    {2, 41, 5, 8, 1, 40, 70},  // 2 x 3 tiles, both partial
    {2, 3, 4, 4, 1, 2, 1},     // one pillar
    {2, 3, 4, 4, 0, 2, 0},     // no pillar: the band is cleared
    {1, 1, 1, 1, 0, 1, 1},     // a 1 x 1 canvas
};

}  // namespace

TEST(ScatterKernels, ForwardFillsTheBandAndLeavesTheRest) {
  std::uint64_t seed = 2000;
  for (const ScatterCase& c : kScatterCases) {
    SCOPED_TRACE(::testing::Message() << "P " << c.pillars << ", C " << c.channels << " at "
                                      << c.channel0 << " of " << c.canvas_channels);
    const Tensor<float> features = normal_tensor({c.pillars, c.channels}, seed++);
    const Tensor<std::int32_t> cells = unique_cells(c.pillars, c.batch, c.height, c.width, seed++);
    Tensor<float> band;
    host::scatter_forward(features, cells, c.batch, c.height, c.width, band);
    // The canvas starts as other data; only the band may change.
    const Tensor<float> before =
        normal_tensor({c.batch, c.canvas_channels, c.height, c.width}, seed++);
    Tensor<float> expected = before;
    for (std::int64_t b = 0; b < c.batch; ++b) {
      for (std::int64_t k = 0; k < c.channels; ++k) {
        for (std::int64_t y = 0; y < c.height; ++y) {
          for (std::int64_t x = 0; x < c.width; ++x) {
            expected(b, c.channel0 + k, y, x) = band(b, k, y, x);
          }
        }
      }
    }
    GuardedArray<float> device_features(features), canvas(before);
    GuardedArray<std::int32_t> device_cells(to_vector(cells));
    const cuda::ScatterCanvas shape{c.batch, c.canvas_channels, c.height, c.width, c.channel0};
    cuda::scatter_forward(device_features.data(), device_cells.data(), c.pillars, c.channels, shape,
                          canvas.data(), nullptr);
    EXPECT_TRUE(same_bits(canvas.download(), expected));
    EXPECT_TRUE(canvas.guards_intact());
  }
}

TEST(ScatterKernels, BackwardGathersTheBand) {
  std::uint64_t seed = 2100;
  for (const ScatterCase& c : kScatterCases) {
    SCOPED_TRACE(::testing::Message() << "P " << c.pillars << ", C " << c.channels);
    const Tensor<std::int32_t> cells = unique_cells(c.pillars, c.batch, c.height, c.width, seed++);
    const Tensor<float> d_canvas =
        normal_tensor({c.batch, c.canvas_channels, c.height, c.width}, seed++);
    Tensor<float> d_band({c.batch, c.channels, c.height, c.width});
    for (std::int64_t b = 0; b < c.batch; ++b) {
      for (std::int64_t k = 0; k < c.channels; ++k) {
        for (std::int64_t y = 0; y < c.height; ++y) {
          for (std::int64_t x = 0; x < c.width; ++x) {
            d_band(b, k, y, x) = d_canvas(b, c.channel0 + k, y, x);
          }
        }
      }
    }
    Tensor<float> expected;
    host::scatter_backward(d_band, cells, expected);
    GuardedArray<float> device_canvas(d_canvas), d_features(c.pillars * c.channels);
    GuardedArray<std::int32_t> device_cells(to_vector(cells));
    const cuda::ScatterCanvas shape{c.batch, c.canvas_channels, c.height, c.width, c.channel0};
    cuda::scatter_backward(device_canvas.data(), shape, device_cells.data(), c.pillars, c.channels,
                           d_features.data(), nullptr);
    EXPECT_TRUE(same_bits(d_features.download(), expected));
    EXPECT_TRUE(d_features.guards_intact());
  }
}

TEST(ScatterKernels, CellsOutsideTheCanvasTouchNothing) {
  // A kernel cannot throw: a cell outside the canvas is skipped (forward) or reads 0 (backward).
  const cuda::ScatterCanvas shape{2, 2, 3, 4, 0};
  const std::vector<std::int32_t> cells = {0, 1, 1, /**/ 2, 0, 0, /**/ 1, 3, 0, /**/ 1, 2, -1};
  const std::vector<float> features = {1, 2, 3, 4, 5, 6, 7, 8};
  GuardedArray<float> device_features(features), canvas(2 * 2 * 3 * 4);
  GuardedArray<std::int32_t> device_cells(cells);
  cuda::scatter_forward(device_features.data(), device_cells.data(), 4, 2, shape, canvas.data(),
                        nullptr);
  std::vector<float> expected(2 * 2 * 3 * 4, 0.0f);
  expected[1 * 4 + 1] = 1.0f;       // pillar 0 at (0, 1, 1), channel 0
  expected[12 + 1 * 4 + 1] = 2.0f;  // channel 1
  EXPECT_TRUE(same_bits(canvas.download(), expected));
  EXPECT_TRUE(canvas.guards_intact());
  GuardedArray<float> d_features(8);
  cuda::scatter_backward(canvas.data(), shape, device_cells.data(), 4, 2, d_features.data(),
                         nullptr);
  EXPECT_TRUE(same_bits(d_features.download(), std::vector<float>{1, 2, 0, 0, 0, 0, 0, 0}));
}

TEST(ScatterKernels, LaunchersCheckTheirArguments) {
  const std::string outside = error_message([] {
    cuda::scatter_forward(nullptr, nullptr, 0, 4, {1, 5, 2, 2, 2}, nullptr, nullptr);
  });
  EXPECT_NE(outside.find("the pillar channels [2, 6) lie outside the canvas's 5 channels"),
            std::string::npos)
      << outside;
  const std::string null_canvas = error_message([] {
    cuda::scatter_forward(nullptr, nullptr, 0, 1, {1, 1, 2, 2, 0}, nullptr, nullptr);
  });
  EXPECT_NE(null_canvas.find("canvas must point to 4 floats"), std::string::npos) << null_canvas;
}

// ---------------------------------------------------------------------------------------------
// MaxPool2d

namespace {

struct PoolCase {
  std::int64_t batch, channels, height, width, offset;
};

const std::vector<PoolCase> kPoolCases = {
    {1, 3, 6, 8, 0},    // even width: float2 rows
    {2, 1, 7, 9, 0},    // odd height and width: the last row and column are dropped
    {1, 1, 1, 5, 0},    // no whole window: empty output, dx all zeros
    {1, 5, 33, 70, 0},  // several tiles, partial ones
    {2, 2, 10, 12, 1},  // misaligned x: scalar rows
    {1, 1, 2, 2, 0},    // one window
};

// Small integers (many ties) with NaN and Inf sprinkled in.
Tensor<float> pool_input(const Shape& shape, std::uint64_t seed) {
  Rng rng(seed);
  Tensor<float> x(shape);
  for (float& v : x) v = static_cast<float>(static_cast<int>(rng.uniform_int(7)) - 3);
  for (std::int64_t i = 0; i < x.numel(); i += 13) x.data()[i] = kNan;
  for (std::int64_t i = 5; i < x.numel(); i += 17) x.data()[i] = -kInf;
  for (std::int64_t i = 11; i < x.numel(); i += 29) x.data()[i] = kInf;
  return x;
}

}  // namespace

TEST(MaxPoolKernels, ForwardAndBackwardMatchTheReferenceBitForBit) {
  std::uint64_t seed = 2200;
  for (const PoolCase& c : kPoolCases) {
    const Shape x_shape{c.batch, c.channels, c.height, c.width};
    SCOPED_TRACE(shape_str(x_shape) + " offset " + std::to_string(c.offset));
    const Tensor<float> x = pool_input(x_shape, seed++);
    Tensor<float> y;
    Tensor<std::int32_t> argmax;
    host::maxpool2d_forward(x, y, &argmax);
    const std::int64_t planes = c.batch * c.channels;
    GuardedArray<float> device_x(x, c.offset), device_y(y.numel(), c.offset);
    GuardedArray<std::int32_t> device_argmax(argmax.numel());
    cuda::maxpool2d_forward(device_x.data(), planes, c.height, c.width, device_y.data(),
                            device_argmax.data(), nullptr);
    EXPECT_TRUE(same_bits(device_y.download(), y));
    EXPECT_TRUE(same_bits(device_argmax.download(), argmax));
    EXPECT_TRUE(device_y.guards_intact());
    EXPECT_TRUE(device_argmax.guards_intact());
    cuda::maxpool2d_forward(device_x.data(), planes, c.height, c.width, device_y.data(), nullptr,
                            nullptr);
    EXPECT_TRUE(same_bits(device_y.download(), y)) << "without argmax";

    const Tensor<float> dy = normal_tensor(y.shape(), seed++);
    Tensor<float> dx;
    host::maxpool2d_backward(dy, argmax, x_shape, dx);
    // dx starts as other data: every element must be written.
    GuardedArray<float> device_dy(dy), device_dx(normal_values(x.numel(), seed++), c.offset);
    cuda::maxpool2d_backward(device_dy.data(), device_argmax.data(), planes, c.height, c.width,
                             device_dx.data(), nullptr);
    EXPECT_TRUE(same_bits(device_dx.download(), dx));
    EXPECT_TRUE(device_dx.guards_intact());
  }
}

TEST(MaxPoolKernels, NanWinsAndTiesKeepTheFirst) {
  const std::vector<float> x = {1,          1,     kNan,       2,     /**/ 5, 5,
                                3,          kNan,  /**/ -kInf, -kInf, 0,      -0.0f,
                                /**/ -kInf, -kInf, -0.0f,      0};
  GuardedArray<float> device_x(x), y(4);
  GuardedArray<std::int32_t> argmax(4);
  cuda::maxpool2d_forward(device_x.data(), 1, 4, 4, y.data(), argmax.data(), nullptr);
  const std::vector<float> values = y.download();
  EXPECT_EQ(values[0], 5.0f) << "window {1, 1, 5, 5}";
  EXPECT_TRUE(std::isnan(values[1])) << "window {NaN, 2, 3, NaN}";
  EXPECT_EQ(values[2], -kInf) << "an all -Inf window";
  EXPECT_EQ(values[3], 0.0f);
  EXPECT_TRUE(same_bits(argmax.download(), std::vector<std::int32_t>{4, 7, 8, 10}))
      << "first of tied maxima, last NaN, -Inf's first element, 0 before -0";
}

// ---------------------------------------------------------------------------------------------
// Bilinear upsampling

TEST(UpsampleKernels, ForwardAndBackwardMatchTheReference) {
  const std::vector<Shape> shapes = {{1, 3, 1, 1},    {2, 1, 1, 5}, {1, 2, 4, 3},
                                     {2, 10, 17, 33}, {1, 1, 2, 2}, {1, 1, 6, 1}};
  std::uint64_t seed = 2300;
  for (const Shape& shape : shapes) {
    SCOPED_TRACE(shape_str(shape));
    const Tensor<float> x = normal_tensor(shape, seed++);
    Tensor<float> y;
    host::upsample_bilinear_forward(x, y);
    const std::int64_t planes = shape[0] * shape[1];
    GuardedArray<float> device_x(x), device_y(y.numel());
    cuda::upsample_bilinear_forward(device_x.data(), planes, shape[2], shape[3], device_y.data(),
                                    nullptr);
    EXPECT_TRUE(close(device_y.download(), y, 1e-6, 1e-6));
    EXPECT_TRUE(device_y.guards_intact());

    const Tensor<float> dy = normal_tensor(y.shape(), seed++);
    Tensor<float> dx;
    host::upsample_bilinear_backward(dy, dx);
    GuardedArray<float> device_dy(dy), device_dx(x.numel());
    cuda::upsample_bilinear_backward(device_dy.data(), planes, shape[2], shape[3], device_dx.data(),
                                     nullptr);
    EXPECT_TRUE(close(device_dx.download(), dx, 1e-6, 1e-5));
    EXPECT_TRUE(device_dx.guards_intact());
  }
}

TEST(UpsampleKernels, HandComputedTwoByTwo) {
  // Along an axis of 2 inputs and 4 outputs the sources are 0, 1/3, 2/3, 1.
  GuardedArray<float> x(std::vector<float>{0, 3, 6, 9}), y(16);
  cuda::upsample_bilinear_forward(x.data(), 1, 2, 2, y.data(), nullptr);
  const std::vector<float> values = y.download();
  EXPECT_FLOAT_EQ(values[0], 0.0f);
  EXPECT_FLOAT_EQ(values[1], 1.0f);
  EXPECT_FLOAT_EQ(values[3], 3.0f);
  EXPECT_FLOAT_EQ(values[4], 2.0f);  // one third of the way down: 6 / 3
  EXPECT_FLOAT_EQ(values[15], 9.0f);
  // The backward of all-ones spreads 16 over the 4 inputs, 4 each by symmetry.
  GuardedArray<float> dy(std::vector<float>(16, 1.0f)), dx(4);
  cuda::upsample_bilinear_backward(dy.data(), 1, 2, 2, dx.data(), nullptr);
  for (const float v : dx.download()) EXPECT_FLOAT_EQ(v, 4.0f);
}

// ---------------------------------------------------------------------------------------------
// Pad + concat

TEST(PadConcatKernels, ForwardAndBackwardMatchTheReferenceBitForBit) {
  const std::vector<cuda::PadConcatShape> cases = {
      {2, 3, 2, 7, 9, 4, 6},    // odd differences: one more padding row/column after
      {1, 2, 3, 8, 8, 8, 8},    // no padding
      {2, 0, 3, 5, 6, 2, 3},    // no skip channels
      {1, 1, 1, 40, 70, 1, 1},  // several tiles, a 1 x 1 up
  };
  std::uint64_t seed = 2400;
  for (const cuda::PadConcatShape& s : cases) {
    const Shape skip_shape{s.batch, s.skip_channels, s.height, s.width};
    const Shape up_shape{s.batch, s.up_channels, s.up_height, s.up_width};
    SCOPED_TRACE(shape_str(skip_shape) + " + " + shape_str(up_shape));
    const Tensor<float> skip = normal_tensor(skip_shape, seed++);
    const Tensor<float> up = normal_tensor(up_shape, seed++);
    Tensor<float> y;
    host::pad_concat_forward(skip, up, y);
    GuardedArray<float> device_skip(skip), device_up(up),
        device_y(normal_values(y.numel(), seed++));  // other data: every element is written
    cuda::pad_concat_forward(device_skip.data(), device_up.data(), s, device_y.data(), nullptr);
    EXPECT_TRUE(same_bits(device_y.download(), y));
    EXPECT_TRUE(device_y.guards_intact());

    const Tensor<float> dy = normal_tensor(y.shape(), seed++);
    Tensor<float> d_skip, d_up;
    host::pad_concat_backward(dy, skip_shape, up_shape, &d_skip, &d_up);
    GuardedArray<float> device_dy(dy), device_d_skip(skip.numel()), device_d_up(up.numel());
    cuda::pad_concat_backward(device_dy.data(), s, device_d_skip.data(), device_d_up.data(),
                              nullptr);
    EXPECT_TRUE(same_bits(device_d_skip.download(), d_skip));
    EXPECT_TRUE(same_bits(device_d_up.download(), d_up));
    EXPECT_TRUE(device_d_skip.guards_intact());
    EXPECT_TRUE(device_d_up.guards_intact());
    GuardedArray<float> only_up(up.numel());
    cuda::pad_concat_backward(device_dy.data(), s, nullptr, only_up.data(), nullptr);
    EXPECT_TRUE(same_bits(only_up.download(), d_up));
  }
}

TEST(PadConcatKernels, LaunchersCheckTheirArguments) {
  const std::string larger = error_message([] {
    cuda::pad_concat_forward(nullptr, nullptr, {1, 1, 1, 4, 4, 5, 4}, nullptr, nullptr);
  });
  EXPECT_NE(larger.find("h <= H and w <= W"), std::string::npos) << larger;
}

// ---------------------------------------------------------------------------------------------
// Elementwise ops and band copies

TEST(ElementwiseKernels, AddInplaceAndScaleMatchHostLoopsBitForBit) {
  for (const std::int64_t n : {0, 1, 3, 33, 1000, 4097}) {
    for (const auto& [offset_a, offset_b] :
         std::vector<std::pair<std::int64_t, std::int64_t>>{{0, 0}, {1, 1}, {3, 3}, {0, 2}}) {
      SCOPED_TRACE(::testing::Message()
                   << "n " << n << ", offsets " << offset_a << " " << offset_b);
      std::vector<float> a = normal_values(n, 2500 + static_cast<std::uint64_t>(n));
      const std::vector<float> b = normal_values(n, 2600 + static_cast<std::uint64_t>(n));
      if (n > 2) a[2] = kNan;
      GuardedArray<float> device_a(a, offset_a), device_b(b, offset_b);
      cuda::add_inplace(device_a.data(), device_b.data(), n, nullptr);
      for (std::size_t i = 0; i < a.size(); ++i) a[i] += b[i];
      EXPECT_TRUE(same_bits(device_a.download(), a));
      cuda::scale(device_a.data(), -0.375f, n, nullptr);
      for (float& v : a) v *= -0.375f;
      EXPECT_TRUE(same_bits(device_a.download(), a));
      EXPECT_TRUE(device_a.guards_intact());
    }
  }
}

TEST(ElementwiseKernels, ChannelBandsCopyBothWays) {
  const std::vector<std::pair<cuda::ChannelBand, std::int64_t>> cases = {
      {{2, 3, 35, 7, 2}, 0},  // S = 35: scalar runs
      {{2, 4, 64, 9, 5}, 0},  // float4 runs
      {{2, 4, 64, 9, 5}, 1},  // misaligned: scalar runs
      {{1, 2, 16, 2, 0}, 0},  // the band is the whole tensor
      {{3, 1, 1, 1, 0}, 0},   // 1 x 1 planes
  };
  std::uint64_t seed = 2700;
  for (const auto& [band, offset] : cases) {
    SCOPED_TRACE(::testing::Message()
                 << "B " << band.batch << ", Cx " << band.channels << " at " << band.channel0
                 << " of " << band.wide_channels << ", S " << band.inner << ", offset " << offset);
    const std::int64_t narrow = band.batch * band.channels * band.inner;
    const std::int64_t wide = band.batch * band.wide_channels * band.inner;
    const std::vector<float> x = normal_values(narrow, seed++);
    const std::vector<float> y_before = normal_values(wide, seed++);
    std::vector<float> expected_y = y_before;
    for (std::int64_t b = 0; b < band.batch; ++b) {
      for (std::int64_t i = 0; i < band.channels * band.inner; ++i) {
        expected_y[static_cast<std::size_t>((b * band.wide_channels + band.channel0) * band.inner +
                                            i)] =
            x[static_cast<std::size_t>(b * band.channels * band.inner + i)];
      }
    }
    GuardedArray<float> device_x(x, offset), device_y(y_before, offset);
    cuda::copy_channels(device_x.data(), band, device_y.data(), nullptr);
    EXPECT_TRUE(same_bits(device_y.download(), expected_y));
    EXPECT_TRUE(device_y.guards_intact());
    GuardedArray<float> back(narrow, offset);
    cuda::extract_channels(device_y.data(), band, back.data(), nullptr);
    EXPECT_TRUE(same_bits(back.download(), x));
    EXPECT_TRUE(back.guards_intact());
  }
}

TEST(ElementwiseKernels, LaunchersCheckTheirArguments) {
  const std::string outside = error_message([] {
    cuda::copy_channels(nullptr, {1, 3, 4, 4, 2}, nullptr, nullptr);
  });
  EXPECT_NE(outside.find("channels [channel0, channel0 + Cx) = [2, 5) inside the 4 channels"),
            std::string::npos)
      << outside;
  const std::string negative = error_message([] { cuda::scale(nullptr, 2.0f, -1, nullptr); });
  EXPECT_NE(negative.find("scale: n = -1"), std::string::npos) << negative;
}

// ---------------------------------------------------------------------------------------------
// Softmax and arg-max

TEST(SoftmaxKernels, SoftmaxMatchesTheReferenceWithNanAndInf) {
  const std::vector<Shape> shapes = {{2, 12, 7, 9}, {1, 1, 3, 5}, {2, 3, 1, 300}};
  std::uint64_t seed = 2800;
  for (const Shape& shape : shapes) {
    SCOPED_TRACE(shape_str(shape));
    Tensor<float> logits = normal_tensor(shape, seed++, 3.0);
    const std::int64_t plane = shape[2] * shape[3];
    const bool specials = shape[1] > 1 && plane > 4;
    if (specials) {
      logits(0, 0, 0, 1) = kNan;                        // a NaN: the cell is NaN
      logits(shape[0] - 1, shape[1] - 1, 0, 2) = kInf;  // +Inf: Inf - Inf, NaN
      logits(0, shape[1] - 1, 0, 3) = -kInf;            // -Inf: probability 0
      for (std::int64_t k = 0; k < shape[1]; ++k) logits(0, k, 0, 4) = -kInf;  // all -Inf: NaN
    }
    Tensor<float> expected;
    host::softmax_channels(logits, expected);
    GuardedArray<float> device_logits(logits), probabilities(logits.numel());
    cuda::softmax_channels(device_logits.data(), shape[0], shape[1], plane, probabilities.data(),
                           nullptr);
    const std::vector<float> actual = probabilities.download();
    EXPECT_TRUE(close(actual, expected, 1e-7, 1e-5));
    EXPECT_TRUE(probabilities.guards_intact());
    if (specials) {
      EXPECT_TRUE(std::isnan(actual[1]));
      EXPECT_EQ(actual[static_cast<std::size_t>((shape[1] - 1) * plane + 3)], 0.0f);
    }
  }
}

TEST(SoftmaxKernels, ArgmaxMatchesTheReferenceBitForBit) {
  const std::vector<Shape> shapes = {{2, 12, 7, 9}, {1, 1, 3, 5}, {2, 5, 1, 300}};
  std::uint64_t seed = 2900;
  for (const Shape& shape : shapes) {
    SCOPED_TRACE(shape_str(shape));
    Rng rng(seed++);
    Tensor<float> logits(shape);
    for (float& v : logits) v = static_cast<float>(rng.uniform_int(4));  // many ties
    for (std::int64_t i = 7; i < logits.numel(); i += 37) logits.data()[i] = kNan;
    for (std::int64_t i = 3; i < logits.numel(); i += 41) logits.data()[i] = kInf;
    Tensor<std::uint8_t> expected;
    host::argmax_class_ids(logits, expected);
    const std::int64_t plane = shape[2] * shape[3];
    GuardedArray<float> device_logits(logits);
    GuardedArray<std::uint8_t> ids(shape[0] * plane);
    cuda::argmax_class_ids(device_logits.data(), shape[0], shape[1], plane, ids.data(), nullptr);
    EXPECT_TRUE(same_bits(ids.download(), expected));
    EXPECT_TRUE(ids.guards_intact());
  }
}

TEST(SoftmaxKernels, ArgmaxByHand) {
  // Four cells of K = 4 logits, channel-major: a tie (the lower channel wins), two NaNs (the
  // first wins), a NaN after +Inf (NaN wins), all -Inf (channel 0 keeps it).
  const std::vector<float> logits = {1,      kNan, kInf, -kInf, /**/ 3, 2, kNan, -kInf,
                                     /**/ 3, kNan, 5,    -kInf, /**/ 0, 1, 5,    -kInf};
  GuardedArray<float> device_logits(logits);
  GuardedArray<std::uint8_t> ids(4);
  cuda::argmax_class_ids(device_logits.data(), 1, 4, 4, ids.data(), nullptr);
  EXPECT_TRUE(same_bits(ids.download(), std::vector<std::uint8_t>{2, 1, 2, 1}));
}

TEST(SoftmaxKernels, ArgmaxPositiveByHand) {
  // Five cells of K = 3 values, channel-major: the largest in the last channel (class 3); a tie
  // of channels 1 and 2 (the lower: class 2); all 0 (class 0); negative and 0 (class 0); NaN on
  // both sides of a positive (the positive: NaN never wins).
  const std::vector<float> values = {0.2f, 1, 0, -1, kNan, /**/ 0.1f, 3, 0, 0, 0.5f,
                                     /**/ 0.7f, 3, 0, -2, kNan};
  const std::vector<std::uint8_t> expected = {3, 2, 0, 0, 2};
  GuardedArray<float> device_values(values);
  GuardedArray<std::uint8_t> ids(5);
  cuda::argmax_positive_class_ids(device_values.data(), 1, 3, 5, ids.data(), nullptr);
  EXPECT_TRUE(same_bits(ids.download(), expected));
  EXPECT_TRUE(ids.guards_intact());
  Tensor<float> host_values({1, 3, 1, 5});
  std::copy(values.begin(), values.end(), host_values.begin());
  Tensor<std::uint8_t> host_ids;
  host::argmax_positive_class_ids(host_values, host_ids);
  EXPECT_TRUE(same_bits(std::vector<std::uint8_t>(host_ids.begin(), host_ids.end()), expected));
}

TEST(MirrorAddKernel, ByHandAndAsTheHost) {
  // One plane of 2 x 3 onto a sum of 1s: each mirror by hand.
  const std::vector<float> x = {1, 2, 3, /**/ 4, 5, 6};
  const std::vector<std::vector<float>> expected = {{2, 3, 4, 5, 6, 7},   // as it is
                                                    {5, 6, 7, 2, 3, 4},   // rows mirrored
                                                    {4, 3, 2, 7, 6, 5},   // columns
                                                    {7, 6, 5, 4, 3, 2}};  // both
  GuardedArray<float> device_x(x);
  for (int f = 0; f < 4; ++f) {
    const bool mirror_y = (f & 1) != 0, mirror_x = (f & 2) != 0;
    GuardedArray<float> sum(std::vector<float>(6, 1.0f));
    cuda::mirror_add(device_x.data(), 1, 2, 3, mirror_y, mirror_x, sum.data(), nullptr);
    EXPECT_TRUE(same_bits(sum.download(), expected[f])) << "flip " << f;
    EXPECT_TRUE(sum.guards_intact());
  }
  // Random planes and odd sizes: the kernel's sum is the host's bit for bit.
  for (const Shape& shape : std::vector<Shape>{{1, 1, 1, 1}, {2, 12, 7, 5}, {1, 3, 9, 16}}) {
    const Tensor<float> pass = kernel_test::normal_tensor(shape, 91);
    for (int f = 0; f < 4; ++f) {
      Tensor<float> host_sum = kernel_test::normal_tensor(shape, 92);
      GuardedArray<float> device_pass(pass), device_sum(host_sum);
      cuda::mirror_add(device_pass.data(), shape[0] * shape[1], shape[2], shape[3], (f & 1) != 0,
                       (f & 2) != 0, device_sum.data(), nullptr);
      host::mirror_add(pass, (f & 1) != 0, (f & 2) != 0, host_sum);
      EXPECT_TRUE(same_bits(device_sum.download(), host_sum)) << shape_str(shape) << " flip " << f;
      EXPECT_TRUE(device_sum.guards_intact());
    }
  }
  const std::string overlap = error_message([&] {
    cuda::mirror_add(device_x.data(), 1, 2, 3, true, false, device_x.data() + 1, nullptr);
  });
  EXPECT_NE(overlap.find("must not overlap"), std::string::npos) << overlap;
}

TEST(SoftmaxKernels, LaunchersCheckTheirArguments) {
  const std::string too_many =
      error_message([] { cuda::argmax_class_ids(nullptr, 1, 256, 4, nullptr, nullptr); });
  EXPECT_NE(too_many.find("1 <= K <= 255"), std::string::npos) << too_many;
  cuda::DeviceBuffer<float> buffer(8);
  const std::string in_place = error_message(
      [&] { cuda::softmax_channels(buffer.data(), 1, 2, 4, buffer.data(), nullptr); });
  EXPECT_NE(in_place.find("not in place"), std::string::npos) << in_place;
}

// ---------------------------------------------------------------------------------------------
// Losses

namespace {

enum class LossKind { CrossEntropy, Bce, CrossEntropyLovasz };

// Class weights as the configs set them: vehicle 2, person, two-wheel, rider 8, others 1.
const std::vector<float> kClassWeights = {0, 2, 8, 8, 8, 1, 1, 1, 1, 1, 1, 1, 1};
// The Lovász term's weight in the combined loss (a data-parallel replica's 1 / R).
constexpr float kLovaszWeight = 0.5f;

Tensor<std::uint8_t> random_labels(const Shape& shape, std::uint64_t seed, double unlabeled) {
  Rng rng(seed);
  Tensor<std::uint8_t> labels(shape);
  for (std::uint8_t& l : labels) {
    l = rng.uniform() < unlabeled ? 0 : static_cast<std::uint8_t>(1 + rng.uniform_int(12));
  }
  return labels;
}

struct DeviceLoss {
  double loss;
  std::vector<float> d_logits;
};

DeviceLoss device_loss(LossKind kind, const Tensor<float>& logits,
                       const Tensor<std::uint8_t>& labels, bool with_gradient) {
  const std::int64_t batch = logits.dim(0), classes = logits.dim(1);
  const std::int64_t plane = logits.dim(2) * logits.dim(3);
  GuardedArray<float> device_logits(logits), weights(kClassWeights), d_logits(logits.numel());
  GuardedArray<std::uint8_t> device_labels(std::vector<std::uint8_t>(labels.begin(), labels.end()));
  GuardedArray<cuda::LossPartial> workspace(cuda::kLossPartials);
  GuardedArray<cuda::LossResult> result(1);
  const auto run = kind == LossKind::Bce ? cuda::bce_loss : cuda::cross_entropy_loss;
  run(device_logits.data(), device_labels.data(), batch, classes, plane, weights.data(),
      with_gradient ? d_logits.data() : nullptr, workspace.data(), result.data(), nullptr);
  if (kind == LossKind::CrossEntropyLovasz) {
    GuardedArray<int> counts(cuda::lovasz_count_ints(classes));
    GuardedArray<double> steps(cuda::lovasz_step_doubles(classes));
    cuda::lovasz_softmax_loss(device_logits.data(), device_labels.data(), batch, classes, plane,
                              kLovaszWeight, with_gradient ? d_logits.data() : nullptr,
                              counts.data(), steps.data(), workspace.data(), result.data(),
                              nullptr);
    EXPECT_TRUE(counts.guards_intact());
    EXPECT_TRUE(steps.guards_intact());
  }
  EXPECT_TRUE(d_logits.guards_intact());
  EXPECT_TRUE(workspace.guards_intact());
  EXPECT_TRUE(result.guards_intact());
  return {cuda::loss_value(result.data(), nullptr), d_logits.download()};
}

double host_loss(LossKind kind, const Tensor<float>& logits, const Tensor<std::uint8_t>& labels,
                 Tensor<float>& d_logits) {
  const std::vector<double> weights(kClassWeights.begin(), kClassWeights.end());
  if (kind == LossKind::Bce) return host::bce_loss(logits, labels, weights, &d_logits);
  const double ce = host::cross_entropy_loss(logits, labels, weights, &d_logits);
  if (kind == LossKind::CrossEntropy) return ce;
  Tensor<float> d_lovasz;
  const double lovasz = host::lovasz_softmax_loss(logits, labels, &d_lovasz);
  for (std::int64_t i = 0; i < d_logits.numel(); ++i) d_logits[i] += kLovaszWeight * d_lovasz[i];
  return ce + kLovaszWeight * lovasz;
}

const char* loss_name(LossKind kind) {
  return kind == LossKind::CrossEntropy ? "cross-entropy"
         : kind == LossKind::Bce        ? "bce"
                                        : "cross-entropy + Lovász";
}

constexpr LossKind kLossKinds[] = {LossKind::CrossEntropy, LossKind::Bce,
                                   LossKind::CrossEntropyLovasz};

}  // namespace

TEST(LossKernels, LossAndGradientMatchTheReference) {
  const std::vector<Shape> shapes = {{2, 12, 9, 11}, {1, 12, 1, 1}, {2, 12, 64, 64}};
  std::uint64_t seed = 3000;
  for (const LossKind kind : kLossKinds) {
    for (const Shape& shape : shapes) {
      SCOPED_TRACE(std::string(loss_name(kind)) + " " + shape_str(shape));
      Tensor<float> logits = normal_tensor(shape, seed++, 4.0);
      Tensor<std::uint8_t> labels = random_labels({shape[0], shape[2], shape[3]}, seed++, 0.3);
      if (shape[2] * shape[3] > 1) {
        labels(0, 0, 1) = 0;  // NaN and Inf logits in an unlabeled cell: no loss, zero gradient
        logits(0, 3, 0, 1) = kNan;
        logits(0, 5, 0, 1) = kInf;
        labels(0, 0, 0) = 1;
        logits(0, 4, 0, 0) = 80.0f;  // large logits stay finite (logsumexp, softplus)
        logits(0, 0, 0, 0) = -80.0f;
      } else {
        labels(0, 0, 0) = 3;
      }
      Tensor<float> expected_gradient;
      const double expected = host_loss(kind, logits, labels, expected_gradient);
      const DeviceLoss actual = device_loss(kind, logits, labels, true);
      // Each cell's logsumexp and softplus are float, here and in the reference, with different
      // exp and log (Eigen's vectorised ones there): a few float roundings of |z| <= 80 per cell.
      EXPECT_NEAR(actual.loss, expected, 1e-5 * std::max(1.0, std::abs(expected)));
      EXPECT_TRUE(close(actual.d_logits, expected_gradient, 1e-9, 1e-5));
      const DeviceLoss loss_only = device_loss(kind, logits, labels, false);
      EXPECT_EQ(loss_only.loss, actual.loss);
    }
  }
}

TEST(LossKernels, NoLabelledCellGivesZeroLossAndGradient) {
  for (const LossKind kind : kLossKinds) {
    SCOPED_TRACE(loss_name(kind));
    const Tensor<float> logits = normal_tensor({2, 12, 3, 5}, 3100);
    const Tensor<std::uint8_t> labels({2, 3, 5});
    const DeviceLoss actual = device_loss(kind, logits, labels, true);
    EXPECT_EQ(actual.loss, 0.0);
    for (const float g : actual.d_logits) EXPECT_EQ(g, 0.0f);
  }
}

TEST(LossKernels, HandComputedCrossEntropy) {
  // One cell, K = 2, logits (0, ln 3): softmax (1/4, 3/4); label 2 with weight 8:
  // loss = 8 * -ln(3/4), gradient 8 * (1/4, 3/4 - 1).
  Tensor<float> logits({1, 2, 1, 1});
  logits(0, 1, 0, 0) = std::log(3.0f);
  GuardedArray<float> device_logits(logits), weights(std::vector<float>{0, 1, 8}), d_logits(2);
  GuardedArray<std::uint8_t> labels(std::vector<std::uint8_t>{2});
  GuardedArray<cuda::LossPartial> workspace(cuda::kLossPartials);
  GuardedArray<cuda::LossResult> result(1);
  cuda::cross_entropy_loss(device_logits.data(), labels.data(), 1, 2, 1, weights.data(),
                           d_logits.data(), workspace.data(), result.data(), nullptr);
  EXPECT_NEAR(cuda::loss_value(result.data(), nullptr), -8.0 * std::log(0.75), 1e-6);
  const std::vector<float> gradient = d_logits.download();
  EXPECT_NEAR(gradient[0], 2.0f, 1e-6);
  EXPECT_NEAR(gradient[1], -2.0f, 1e-6);
}

TEST(LossKernels, SameBitsForEveryRunAndThreadCount) {
  const Tensor<float> logits = normal_tensor({2, 12, 64, 64}, 3200, 3.0);
  const Tensor<std::uint8_t> labels = random_labels({2, 64, 64}, 3201, 0.2);
  const int threads = omp_get_max_threads();
  for (const LossKind kind : kLossKinds) {
    omp_set_num_threads(threads);
    const DeviceLoss reference = device_loss(kind, logits, labels, true);
    for (const int t : {1, 3}) {
      omp_set_num_threads(t);
      const DeviceLoss again = device_loss(kind, logits, labels, true);
      EXPECT_EQ(std::bit_cast<std::uint64_t>(again.loss),
                std::bit_cast<std::uint64_t>(reference.loss))
          << loss_name(kind) << ", " << t << " threads";
      EXPECT_TRUE(same_bits(again.d_logits, reference.d_logits));
    }
  }
  omp_set_num_threads(threads);
}

TEST(LossKernels, LabelsOutsideTheClassesAreReported) {
  const Tensor<float> logits = normal_tensor({1, 12, 2, 3}, 3300);
  Tensor<std::uint8_t> labels = random_labels({1, 2, 3}, 3301, 0.0);
  labels(0, 1, 2) = 13;
  labels(0, 0, 0) = 200;
  const std::string message =
      error_message([&] { device_loss(LossKind::Bce, logits, labels, true); });
  EXPECT_NE(message.find("loss: 2 labels are not class ids 0..12"), std::string::npos) << message;
}

TEST(LossKernels, LovaszLauncherChecksItsArguments) {
  GuardedArray<float> logits(24), d_logits(24);
  GuardedArray<std::uint8_t> labels(std::vector<std::uint8_t>{1, 2});
  GuardedArray<cuda::LossPartial> workspace(cuda::kLossPartials);
  GuardedArray<cuda::LossResult> result(1);
  GuardedArray<int> counts(cuda::lovasz_count_ints(12));
  GuardedArray<double> steps(cuda::lovasz_step_doubles(12));
  const auto run = [&](float weight, int* c, double* s) {
    return error_message([&] {
      cuda::lovasz_softmax_loss(logits.data(), labels.data(), 1, 12, 2, weight, d_logits.data(), c,
                                s, workspace.data(), result.data(), nullptr);
    });
  };
  EXPECT_NE(run(1.0f, nullptr, steps.data()).find("lovasz_softmax_loss: counts (98316 ints) and "
                                                  "steps (49152 doubles) must be device memory"),
            std::string::npos);
  EXPECT_NE(run(-1.0f, counts.data(), steps.data()).find("a finite weight >= 0, given -1"),
            std::string::npos);
  EXPECT_NE(run(kNan, counts.data(), steps.data()).find("a finite weight >= 0"), std::string::npos);
}

// ---------------------------------------------------------------------------------------------
// AdamW

TEST(AdamKernels, StepMatchesTheReference) {
  const host::AdamOptions host_options{1e-3, 0.9, 0.99, 1e-8, 0.01};
  const cuda::AdamOptions options{1e-3, 0.9, 0.99, 1e-8, 0.01};
  for (const std::int64_t n : {1, 7, 1000, 4099}) {
    for (const std::int64_t offset : {0, 1, 2}) {
      for (const std::int64_t step : {1, 7}) {
        SCOPED_TRACE(::testing::Message()
                     << "n " << n << ", offset " << offset << ", step " << step);
        const auto seed = static_cast<std::uint64_t>(3400 + n + 10 * offset + step);
        std::vector<float> params = normal_values(n, seed);
        const std::vector<float> grads = normal_values(n, seed + 1, 0.1);
        std::vector<float> m = normal_values(n, seed + 2, 0.01);
        std::vector<float> v = normal_values(n, seed + 3, 0.001);
        for (float& x : v) x = x * x;
        // Mixed alignments: the grads one float further take the scalar path.
        GuardedArray<float> device_params(params, offset), device_grads(grads, offset + (n % 2)),
            device_m(m, offset), device_v(v, offset);
        cuda::adam_step(device_params.data(), device_grads.data(), device_m.data(), device_v.data(),
                        n, step, options, nullptr);
        host::adam_step<float>(params, grads, m, v, step, host_options);
        // m = beta1 m + (1 - beta1) g cancels where the two terms (|.| < 0.05) nearly meet; a
        // fused multiply-add on one side rounds once less: an ulp of the terms, not of m. The
        // step lr m / sqrt(v) carries that 1e-8 on into p (lr 1e-3, sqrt(v) >= ~1e-4).
        EXPECT_TRUE(test::all_close(device_params.download().data(), params.data(), n, 1e-7, 1e-6));
        EXPECT_TRUE(test::all_close(device_m.download().data(), m.data(), n, 1e-8, 1e-6));
        EXPECT_TRUE(test::all_close(device_v.download().data(), v.data(), n, 1e-15, 1e-6));
        for (const GuardedArray<float>* a : {&device_params, &device_m, &device_v}) {
          EXPECT_TRUE(a->guards_intact());
        }
      }
    }
  }
}

TEST(AdamKernels, LauncherChecksItsArguments) {
  const std::string step =
      error_message([] { cuda::adam_step(nullptr, nullptr, nullptr, nullptr, 0, 0, {}, nullptr); });
  EXPECT_NE(step.find("expected step >= 1"), std::string::npos) << step;
  const std::string beta = error_message([] {
    cuda::adam_step(nullptr, nullptr, nullptr, nullptr, 0, 1, {1e-3, 1.0, 0.999, 1e-8, 0.0},
                    nullptr);
  });
  EXPECT_NE(beta.find("beta1, beta2 in [0, 1)"), std::string::npos) << beta;
  cuda::adam_step(nullptr, nullptr, nullptr, nullptr, 0, 1, {}, nullptr);  // nothing to do
}
