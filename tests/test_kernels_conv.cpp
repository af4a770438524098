// kernels/conv2d.cu and kernels/conv_transpose2d.cu, run on the CUDA emulation, against the CPU
// reference (host/conv2d, host/conv_transpose2d) evaluated in double: forward, dx, dw and db at
// shapes that are not multiples of the tiles (both the 16-row and the 64-row tile, several row
// and column tiles, one and many splits of the weight gradient), 1x1, 3x3 and 5x5 kernels with
// and without padding (a 1x1 kernel with pad 1 too, whose input gradient crops), 1x1 images, an
// empty batch, with and without bias, pointers off the float4 alignment; guard words around
// every output and the workspace; NaN reaching exactly the outputs that depend on it; the same
// bits on every run and OpenMP thread count; the launchers' argument checks; FastDivmod.
//
// Tolerance: |kernel - reference| <= atol + rtol |reference| per element with rtol = 1e-5 and
// atol = 1e-7 K for a sum of K products of U(-1, 1) values: float32 rounds every partial sum
// (of size ~ sqrt(k) / 3, so by ~ 1e-8 sqrt(K) each), and those errors add up like a random walk
// to a standard deviation of ~ 1e-8 K; atol leaves room for the worst of 10^5 elements, and is
// still orders of magnitude below what a wrong tap or a lost term would cost. The worst element
// of each comparison is printed.
#include <gtest/gtest.h>
#include <omp.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include <fmt/format.h>

#include "core/error.hpp"
#include "core/rng.hpp"
#include "core/tensor.hpp"
#include "host/conv2d.hpp"
#include "host/conv_transpose2d.hpp"
#include "kernels/common.cuh"
#include "kernels/conv2d.cuh"
#include "kernels/conv_transpose2d.cuh"
#include "kernels/device_buffer.hpp"
#ifdef PILLARSEG_CUDA_EMULATION
#include "kernels/gemm_tile.cuh"  // device code: only the emulated build compiles it on the host
#endif
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using cuda::DeviceBuffer;

namespace {

constexpr std::int64_t kGuardFloats = 16;
constexpr std::uint32_t kGuardBits = 0x7FC0DEADu;  // a NaN payload no kernel produces
constexpr double kRtol = 1e-5;
constexpr double kAtolPerTerm = 1e-7;

// n floats of device memory at `offset` floats past a 64-byte boundary (offset 1: every pointer
// off the float4 alignment), with kGuardFloats guard words before and after; the n floats start
// as guard words too, so reading one before writing it shows up as NaN.
class GuardedDeviceArray {
 public:
  GuardedDeviceArray(std::int64_t n, std::int64_t offset)
      : n_(n), offset_(offset), storage_(static_cast<size_t>(2 * kGuardFloats + offset + n)) {
    storage_.copy_from_host(std::vector<float>(storage_.size(), std::bit_cast<float>(kGuardBits)));
  }
  GuardedDeviceArray(const std::vector<float>& values, std::int64_t offset)
      : GuardedDeviceArray(static_cast<std::int64_t>(values.size()), offset) {
    upload(values);
  }
  float* data() { return storage_.data() + kGuardFloats + offset_; }
  std::int64_t size() const { return n_; }
  void upload(const std::vector<float>& values) {
    PS_CUDA_CHECK(
        cudaMemcpy(data(), values.data(), values.size() * sizeof(float), cudaMemcpyHostToDevice));
  }
  std::vector<float> download() const {
    const std::vector<float> all = storage_.to_host();
    return std::vector<float>(all.begin() + kGuardFloats + offset_,
                              all.begin() + kGuardFloats + offset_ + n_);
  }
  ::testing::AssertionResult guards_intact() const {
    const std::vector<float> all = storage_.to_host();
    for (size_t i = 0; i < all.size(); ++i) {
      const auto inside = static_cast<std::int64_t>(i) - kGuardFloats - offset_;
      if (inside >= 0 && inside < n_) continue;
      if (std::bit_cast<std::uint32_t>(all[i]) != kGuardBits) {
        return ::testing::AssertionFailure() << "guard word " << i << " (element " << inside
                                             << " of " << n_ << ") was overwritten with " << all[i];
      }
    }
    return ::testing::AssertionSuccess();
  }

 private:
  std::int64_t n_;
  std::int64_t offset_;
  DeviceBuffer<float> storage_;
};

std::vector<float> random_values(std::int64_t n, std::uint64_t seed) {
  Rng rng(seed);
  std::vector<float> values(static_cast<size_t>(n));
  for (float& v : values) v = static_cast<float>(rng.uniform(-1.0, 1.0));
  return values;
}

TensorD to_tensor(const std::vector<float>& values, const Shape& shape) {
  TensorD t(shape);
  for (std::int64_t i = 0; i < t.numel(); ++i) t[i] = values[static_cast<size_t>(i)];
  return t;
}

std::vector<float> to_floats(const TensorD& t) {
  std::vector<float> values(static_cast<size_t>(t.numel()));
  for (std::int64_t i = 0; i < t.numel(); ++i)
    values[static_cast<size_t>(i)] = static_cast<float>(t[i]);
  return values;
}

// all_close with atol = kAtolPerTerm * terms and rtol = kRtol; prints the worst element's error
// and its share of the tolerance.
::testing::AssertionResult matches_reference(const char* what, const std::vector<float>& actual,
                                             const std::vector<float>& expected,
                                             std::int64_t terms) {
  const double atol = kAtolPerTerm * static_cast<double>(std::max<std::int64_t>(terms, 1));
  double worst_share = 0.0;
  size_t worst = 0;
  for (size_t i = 0; i < expected.size() && i < actual.size(); ++i) {
    if (!std::isfinite(expected[i]) || !std::isfinite(actual[i])) continue;
    const double error = std::abs(static_cast<double>(actual[i]) - expected[i]);
    const double share = error / (atol + kRtol * std::abs(expected[i]));
    if (share > worst_share) worst_share = share, worst = i;
  }
  if (!expected.empty() && actual.size() == expected.size()) {
    std::printf(
        "    %-3s worst error %.3g at %zu (|ref| %.3g, K = %lld): %.0f%% of the tolerance\n", what,
        std::abs(static_cast<double>(actual[worst]) - expected[worst]), worst,
        std::abs(expected[worst]), static_cast<long long>(terms), 100.0 * worst_share);
  }
  if (actual.size() != expected.size()) {
    return ::testing::AssertionFailure()
           << what << ": " << actual.size() << " elements, expected " << expected.size();
  }
  return test::all_close(actual.data(), expected.data(), static_cast<std::int64_t>(actual.size()),
                         atol, kRtol)
         << " (" << what << ")";
}

// Bitwise equality (NaN payloads included), naming the first differing element.
::testing::AssertionResult same_bits(const std::vector<float>& a, const std::vector<float>& b) {
  if (a.size() != b.size()) return ::testing::AssertionFailure() << a.size() << " != " << b.size();
  for (size_t i = 0; i < a.size(); ++i) {
    if (std::bit_cast<std::uint32_t>(a[i]) != std::bit_cast<std::uint32_t>(b[i])) {
      return ::testing::AssertionFailure() << "element " << i << ": " << a[i] << " != " << b[i];
    }
  }
  return ::testing::AssertionSuccess();
}

std::string error_message(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

// ---- conv2d ----

struct ConvCase {
  const char* name;
  cuda::Conv2dShape shape;
  bool bias;
  std::int64_t offset;  // floats past the float4 alignment of every buffer
};

// {batch, I, H, W, O, k, pad}
const ConvCase kConvCases[] = {
    {"B2_I5_O7_13x9_k3p1_bias", {2, 5, 13, 9, 7, 3, 1}, true, 0},
    {"B2_I5_O7_13x9_k3p1_misaligned", {2, 5, 13, 9, 7, 3, 1}, false, 1},
    {"B1_I64_O3_16x12_k1p0_bias", {1, 64, 16, 12, 3, 1, 0}, true, 0},
    {"B3_I6_O5_1x1_k3p1_bias", {3, 6, 1, 1, 5, 3, 1}, true, 0},
    {"B2_I3_O4_1x1_k1p0", {2, 3, 1, 1, 4, 1, 0}, false, 0},
    {"B2_I20_O70_11x17_k1p0_bias", {2, 20, 11, 17, 70, 1, 0}, true, 0},
    {"B1_I9_O17_10x7_k3p0", {1, 9, 10, 7, 17, 3, 0}, false, 0},
    {"B2_I4_O6_5x6_k1p1_bias", {2, 4, 5, 6, 6, 1, 1}, true, 1},
    {"B1_I3_O5_9x8_k5p2_bias", {1, 3, 9, 8, 5, 5, 2}, true, 0},
    {"B2_I32_O48_40x30_k3p1_bias", {2, 32, 40, 30, 48, 3, 1}, true, 0},
};

struct ConvTensors {
  std::vector<float> x, w, bias, dy;
};

ConvTensors conv_inputs(const cuda::Conv2dShape& s, std::uint64_t seed) {
  const std::int64_t k = s.kernel;
  return ConvTensors{
      random_values(s.batch * s.in_channels * s.height * s.width, seed),
      random_values(s.out_channels * s.in_channels * k * k, seed + 1),
      random_values(s.out_channels, seed + 2),
      random_values(s.batch * s.out_channels * s.out_height() * s.out_width(), seed + 3)};
}

struct ConvResults {
  std::vector<float> y, dx, dw, db;
};

// The four passes on the emulated device, each output between guard words (checked here).
ConvResults run_conv_kernels(const cuda::Conv2dShape& s, const ConvTensors& in, bool bias,
                             std::int64_t offset) {
  GuardedDeviceArray x(in.x, offset), w(in.w, offset), b(in.bias, offset), dy(in.dy, offset);
  GuardedDeviceArray y(static_cast<std::int64_t>(in.dy.size()), offset);
  GuardedDeviceArray dx(static_cast<std::int64_t>(in.x.size()), offset);
  GuardedDeviceArray dw(static_cast<std::int64_t>(in.w.size()), offset);
  GuardedDeviceArray db(s.out_channels, offset);
  const auto workspace_floats = cuda::conv2d_backward_weights_workspace(s);
  GuardedDeviceArray workspace(static_cast<std::int64_t>(workspace_floats), offset);

  cuda::conv2d_forward(x.data(), w.data(), bias ? b.data() : nullptr, y.data(), s, nullptr);
  cuda::conv2d_backward_data(dy.data(), w.data(), dx.data(), s, nullptr);
  cuda::conv2d_backward_weights(x.data(), dy.data(), dw.data(), bias ? db.data() : nullptr, s,
                                workspace.data(), workspace_floats, nullptr);
  for (const GuardedDeviceArray* out : {&y, &dx, &dw, &db, &workspace}) {
    EXPECT_TRUE(out->guards_intact());
  }
  EXPECT_TRUE(same_bits(x.download(), in.x)) << "the input x must not change";
  EXPECT_TRUE(same_bits(dy.download(), in.dy)) << "the input dy must not change";
  return ConvResults{y.download(), dx.download(), dw.download(),
                     bias ? db.download() : std::vector<float>{}};
}

// host/conv2d in double.
ConvResults run_conv_reference(const cuda::Conv2dShape& s, const ConvTensors& in, bool bias) {
  const TensorD x = to_tensor(in.x, {s.batch, s.in_channels, s.height, s.width});
  const TensorD w = to_tensor(in.w, {s.out_channels, s.in_channels, s.kernel, s.kernel});
  const TensorD b = to_tensor(in.bias, {s.out_channels});
  const TensorD dy = to_tensor(in.dy, {s.batch, s.out_channels, s.out_height(), s.out_width()});
  TensorD y, dx, dw, db;
  host::conv2d_forward(x, w, bias ? &b : nullptr, static_cast<int>(s.pad), y);
  host::conv2d_backward(x, w, dy, static_cast<int>(s.pad), &dx, &dw, &db);
  return ConvResults{to_floats(y), to_floats(dx), to_floats(dw),
                     bias ? to_floats(db) : std::vector<float>{}};
}

class Conv2dKernels : public ::testing::TestWithParam<ConvCase> {};

TEST_P(Conv2dKernels, MatchTheHostReference) {
  const ConvCase& c = GetParam();
  const cuda::Conv2dShape& s = c.shape;
  const ConvTensors in = conv_inputs(s, 100);
  const ConvResults actual = run_conv_kernels(s, in, c.bias, c.offset);
  const ConvResults expected = run_conv_reference(s, in, c.bias);
  const std::int64_t k2 = s.kernel * s.kernel;
  const std::int64_t pixels = s.batch * s.out_height() * s.out_width();
  EXPECT_TRUE(matches_reference("y", actual.y, expected.y, s.in_channels * k2 + 1));
  EXPECT_TRUE(matches_reference("dx", actual.dx, expected.dx, s.out_channels * k2));
  EXPECT_TRUE(matches_reference("dw", actual.dw, expected.dw, pixels));
  EXPECT_TRUE(matches_reference("db", actual.db, expected.db, pixels));
}

INSTANTIATE_TEST_SUITE_P(Shapes, Conv2dKernels, ::testing::ValuesIn(kConvCases),
                         [](const ::testing::TestParamInfo<ConvCase>& case_info) {
                           return std::string(case_info.param.name);
                         });

TEST(Conv2dKernelsWorkspace, SplitsTheBatchPixelsIntoChunks) {
  // M = 48 rows (wide tile) x N = 288 taps: 1 x 5 tiles, so 1024 / 5 splits are wanted, but
  // 2400 pixels allow only ceil(2400 / 256) = 10 chunks (of 240 pixels, 15 slices each).
  const cuda::Conv2dShape s{2, 32, 40, 30, 48, 3, 1};
  EXPECT_EQ(cuda::conv2d_backward_weights_workspace(s), 10u * (48 * 32 * 9 + 48));
  // M = 7 (narrow tile) x N = 45: one tile; 234 pixels make a single chunk.
  EXPECT_EQ(cuda::conv2d_backward_weights_workspace({2, 5, 13, 9, 7, 3, 1}), 7u * 45 + 7);
  EXPECT_EQ(cuda::conv2d_backward_weights_workspace({0, 5, 13, 9, 7, 3, 1}), 0u);
}

TEST(Conv2dKernelsNan, ReachesExactlyTheOutputsThatDependOnIt) {
  const cuda::Conv2dShape s{2, 5, 13, 9, 7, 3, 1};
  ConvTensors in = conv_inputs(s, 7);
  const float nan = std::numeric_limits<float>::quiet_NaN();
  // x[1, 2, 4, 0]: read by outputs (oy, ox) in [3, 5] x [0, 1] of image 1, every channel o,
  // through taps ky in [0, 2], kx in [0, 1] of input channel 2.
  in.x[static_cast<size_t>(((1 * 5 + 2) * 13 + 4) * 9 + 0)] = nan;
  // dy[0, 3, 12, 8] (the last pixel): reaches dx at (y, x) in [11, 12] x [7, 8] of image 0.
  in.dy[static_cast<size_t>(((0 * 7 + 3) * 13 + 12) * 9 + 8)] = nan;
  const ConvResults actual = run_conv_kernels(s, in, true, 0);
  const ConvResults expected = run_conv_reference(s, in, true);
  const auto nan_count = [](const std::vector<float>& v) {
    return std::count_if(v.begin(), v.end(), [](float f) { return std::isnan(f); });
  };
  EXPECT_EQ(nan_count(actual.y), 7 * 3 * 2);
  EXPECT_EQ(nan_count(actual.dx), 5 * 2 * 2);
  // dw: the x NaN through 3 x 2 taps for every o; the dy NaN through every tap of channel 3.
  EXPECT_EQ(nan_count(actual.dw), 7 * 3 * 2 + 5 * 9 - 3 * 2);
  EXPECT_EQ(nan_count(actual.db), 1);
  // The NaNs sit where the reference has them, and the other elements match it.
  EXPECT_TRUE(matches_reference("y", actual.y, expected.y, 5 * 9 + 1));
  EXPECT_TRUE(matches_reference("dx", actual.dx, expected.dx, 7 * 9));
  EXPECT_TRUE(matches_reference("dw", actual.dw, expected.dw, 2 * 13 * 9));
  EXPECT_TRUE(matches_reference("db", actual.db, expected.db, 2 * 13 * 9));
}

TEST(Conv2dKernelsDeterminism, SameBitsForEveryRunAndThreadCount) {
  for (const cuda::Conv2dShape& s :
       {cuda::Conv2dShape{2, 32, 40, 30, 48, 3, 1}, cuda::Conv2dShape{2, 5, 13, 9, 7, 3, 1}}) {
    const ConvTensors in = conv_inputs(s, 11);
    const ConvResults first = run_conv_kernels(s, in, true, 0);
    const int threads = omp_get_max_threads();
    for (const int t : {1, 3}) {
      omp_set_num_threads(t);
      const ConvResults again = run_conv_kernels(s, in, true, 0);
      EXPECT_TRUE(same_bits(again.y, first.y)) << t << " threads";
      EXPECT_TRUE(same_bits(again.dx, first.dx)) << t << " threads";
      EXPECT_TRUE(same_bits(again.dw, first.dw)) << t << " threads";
      EXPECT_TRUE(same_bits(again.db, first.db)) << t << " threads";
    }
    omp_set_num_threads(threads);
  }
}

TEST(Conv2dKernelsEdges, EmptyBatchZeroesTheParameterGradients) {
  const cuda::Conv2dShape s{0, 4, 6, 5, 3, 3, 1};
  GuardedDeviceArray x(0, 0), dy(0, 0), y(0, 0), dx(0, 0);
  GuardedDeviceArray w(random_values(3 * 4 * 9, 1), 0);
  GuardedDeviceArray dw(random_values(3 * 4 * 9, 2), 0), db(random_values(3, 3), 0);
  ASSERT_EQ(cuda::conv2d_backward_weights_workspace(s), 0u);
  cuda::conv2d_forward(x.data(), w.data(), nullptr, y.data(), s, nullptr);
  cuda::conv2d_backward_data(dy.data(), w.data(), dx.data(), s, nullptr);
  cuda::conv2d_backward_weights(x.data(), dy.data(), dw.data(), db.data(), s, nullptr, 0, nullptr);
  EXPECT_TRUE(same_bits(dw.download(), std::vector<float>(3 * 4 * 9, 0.0f)));
  EXPECT_TRUE(same_bits(db.download(), std::vector<float>(3, 0.0f)));
  for (const GuardedDeviceArray* out : {&y, &dx, &dw, &db}) EXPECT_TRUE(out->guards_intact());
}

TEST(Conv2dKernelsEdges, NoInputChannelsGiveTheBias) {
  const cuda::Conv2dShape s{2, 0, 3, 4, 5, 3, 1};
  const std::vector<float> bias = {1.0f, -2.0f, 0.5f, 0.0f, 3.0f};
  GuardedDeviceArray x(0, 0), w(0, 0), b(bias, 0), y(2 * 5 * 3 * 4, 0);
  cuda::conv2d_forward(x.data(), w.data(), b.data(), y.data(), s, nullptr);
  const std::vector<float> out = y.download();
  for (std::int64_t i = 0; i < y.size(); ++i) {
    ASSERT_EQ(out[static_cast<size_t>(i)], bias[static_cast<size_t>(i / 12 % 5)]) << i;
  }
  EXPECT_TRUE(y.guards_intact());
}

TEST(Conv2dKernelsArguments, LaunchersSayWhatIsWrong) {
  const cuda::Conv2dShape s{1, 2, 4, 4, 3, 3, 1};
  DeviceBuffer<float> x(32), w(54), y(48), dw(54), workspace(1000);
  const auto message = [](const std::function<void()>& fn) { return error_message(fn); };
  EXPECT_NE(message([&] {
              cuda::conv2d_forward(nullptr, w.data(), nullptr, y.data(), s, nullptr);
            }).find("conv2d_forward: x is null but must point to 32 floats"),
            std::string::npos);
  EXPECT_NE(message([&] {
              cuda::conv2d_forward(x.data(), w.data(), nullptr, x.data(), s, nullptr);
            }).find("overlap"),
            std::string::npos);
  const cuda::Conv2dShape too_small{1, 2, 1, 1, 3, 3, 0};
  EXPECT_NE(message([&] {
              cuda::conv2d_forward(x.data(), w.data(), nullptr, y.data(), too_small, nullptr);
            }).find("needs an image of at least 3x3 (H x W), got 1x1"),
            std::string::npos);
  const cuda::Conv2dShape negative_pad{1, 2, 4, 4, 3, 3, -1};
  EXPECT_NE(message([&] {
              cuda::conv2d_backward_data(y.data(), w.data(), x.data(), negative_pad, nullptr);
            }).find("pad >= 0"),
            std::string::npos);
  const std::size_t needed = cuda::conv2d_backward_weights_workspace(s);
  const std::string short_workspace = message([&] {
    cuda::conv2d_backward_weights(x.data(), y.data(), dw.data(), nullptr, s, workspace.data(),
                                  needed - 1, nullptr);
  });
  EXPECT_NE(short_workspace.find(
                fmt::format("conv2d_backward_weights: the workspace must hold "
                            "conv2d_backward_weights_workspace(shape) = {} floats, got {} floats",
                            needed, needed - 1)),
            std::string::npos)
      << short_workspace;
  const cuda::Conv2dShape huge{1 << 16, 1 << 10, 64, 64, 1, 1, 0};
  EXPECT_NE(message([&] {
              cuda::conv2d_forward(x.data(), w.data(), nullptr, y.data(), huge, nullptr);
            }).find("the kernels index with int"),
            std::string::npos);
}

// ---- conv_transpose2d ----

struct ConvTransposeCase {
  const char* name;
  cuda::ConvTranspose2dShape shape;
  bool bias;
  std::int64_t offset;
};

// {batch, I, H, W, O}
const ConvTransposeCase kConvTransposeCases[] = {
    {"B2_I5_O7_6x5_bias", {2, 5, 6, 5, 7}, true, 0},
    {"B2_I5_O3_6x5_misaligned", {2, 5, 6, 5, 3}, false, 1},
    {"B1_I32_O16_12x8_bias", {1, 32, 12, 8, 16}, true, 0},
    {"B3_I4_O2_1x1", {3, 4, 1, 1, 2}, false, 0},
    {"B2_I24_O20_9x13_bias", {2, 24, 9, 13, 20}, true, 0},
    {"B2_I40_O8_20x16_bias", {2, 40, 20, 16, 8}, true, 0},
};

struct ConvTransposeTensors {
  std::vector<float> x, w, bias, dy;
};

ConvTransposeTensors conv_transpose_inputs(const cuda::ConvTranspose2dShape& s,
                                           std::uint64_t seed) {
  return ConvTransposeTensors{
      random_values(s.batch * s.in_channels * s.height * s.width, seed),
      random_values(s.in_channels * s.out_channels * 4, seed + 1),
      random_values(s.out_channels, seed + 2),
      random_values(s.batch * s.out_channels * s.out_height() * s.out_width(), seed + 3)};
}

ConvResults run_conv_transpose_kernels(const cuda::ConvTranspose2dShape& s,
                                       const ConvTransposeTensors& in, bool bias,
                                       std::int64_t offset) {
  GuardedDeviceArray x(in.x, offset), w(in.w, offset), b(in.bias, offset), dy(in.dy, offset);
  GuardedDeviceArray y(static_cast<std::int64_t>(in.dy.size()), offset);
  GuardedDeviceArray dx(static_cast<std::int64_t>(in.x.size()), offset);
  GuardedDeviceArray dw(static_cast<std::int64_t>(in.w.size()), offset);
  GuardedDeviceArray db(s.out_channels, offset);
  const auto workspace_floats = cuda::conv_transpose2d_backward_weights_workspace(s);
  GuardedDeviceArray workspace(static_cast<std::int64_t>(workspace_floats), offset);

  cuda::conv_transpose2d_forward(x.data(), w.data(), bias ? b.data() : nullptr, y.data(), s,
                                 nullptr);
  cuda::conv_transpose2d_backward_data(dy.data(), w.data(), dx.data(), s, nullptr);
  cuda::conv_transpose2d_backward_weights(x.data(), dy.data(), dw.data(),
                                          bias ? db.data() : nullptr, s, workspace.data(),
                                          workspace_floats, nullptr);
  for (const GuardedDeviceArray* out : {&y, &dx, &dw, &db, &workspace}) {
    EXPECT_TRUE(out->guards_intact());
  }
  return ConvResults{y.download(), dx.download(), dw.download(),
                     bias ? db.download() : std::vector<float>{}};
}

ConvResults run_conv_transpose_reference(const cuda::ConvTranspose2dShape& s,
                                         const ConvTransposeTensors& in, bool bias) {
  const TensorD x = to_tensor(in.x, {s.batch, s.in_channels, s.height, s.width});
  const TensorD w = to_tensor(in.w, {s.in_channels, s.out_channels, 2, 2});
  const TensorD b = to_tensor(in.bias, {s.out_channels});
  const TensorD dy = to_tensor(in.dy, {s.batch, s.out_channels, s.out_height(), s.out_width()});
  TensorD y, dx, dw, db;
  host::conv_transpose2d_forward(x, w, bias ? &b : nullptr, y);
  host::conv_transpose2d_backward(x, w, dy, &dx, &dw, &db);
  return ConvResults{to_floats(y), to_floats(dx), to_floats(dw),
                     bias ? to_floats(db) : std::vector<float>{}};
}

class ConvTranspose2dKernels : public ::testing::TestWithParam<ConvTransposeCase> {};

TEST_P(ConvTranspose2dKernels, MatchTheHostReference) {
  const ConvTransposeCase& c = GetParam();
  const cuda::ConvTranspose2dShape& s = c.shape;
  const ConvTransposeTensors in = conv_transpose_inputs(s, 200);
  const ConvResults actual = run_conv_transpose_kernels(s, in, c.bias, c.offset);
  const ConvResults expected = run_conv_transpose_reference(s, in, c.bias);
  const std::int64_t pixels = s.batch * s.height * s.width;
  EXPECT_TRUE(matches_reference("y", actual.y, expected.y, s.in_channels + 1));
  EXPECT_TRUE(matches_reference("dx", actual.dx, expected.dx, 4 * s.out_channels));
  EXPECT_TRUE(matches_reference("dw", actual.dw, expected.dw, pixels));
  EXPECT_TRUE(matches_reference("db", actual.db, expected.db, 4 * pixels));
}

INSTANTIATE_TEST_SUITE_P(Shapes, ConvTranspose2dKernels, ::testing::ValuesIn(kConvTransposeCases),
                         [](const ::testing::TestParamInfo<ConvTransposeCase>& case_info) {
                           return std::string(case_info.param.name);
                         });

TEST(ConvTranspose2dKernelsByHand, OneInputChannelCopiesTheKernel) {
  // x (1, 1, 1, 2) = [2, -1], w (1, 1, 2, 2) = [[1, 2], [3, 4]], bias 0.5:
  // y = [[2, 4, -1, -2], [6, 8, -3, -4]] + 0.5.
  const cuda::ConvTranspose2dShape s{1, 1, 1, 2, 1};
  GuardedDeviceArray x({2.0f, -1.0f}, 0), w({1.0f, 2.0f, 3.0f, 4.0f}, 0),
      b(std::vector<float>{0.5f}, 0), y(8, 0);
  cuda::conv_transpose2d_forward(x.data(), w.data(), b.data(), y.data(), s, nullptr);
  EXPECT_TRUE(same_bits(y.download(), {2.5f, 4.5f, -0.5f, -1.5f, 6.5f, 8.5f, -2.5f, -3.5f}));
  EXPECT_TRUE(y.guards_intact());
}

TEST(ConvTranspose2dKernelsNan, ReachesExactlyTheOutputsThatDependOnIt) {
  const cuda::ConvTranspose2dShape s{2, 5, 6, 5, 7};
  ConvTransposeTensors in = conv_transpose_inputs(s, 9);
  const float nan = std::numeric_limits<float>::quiet_NaN();
  in.x[static_cast<size_t>(((1 * 5 + 4) * 6 + 2) * 5 + 4)] = nan;      // x[1, 4, 2, 4]
  in.dy[static_cast<size_t>(((0 * 7 + 6) * 12 + 11) * 10 + 0)] = nan;  // dy[0, 6, 11, 0]
  const ConvResults actual = run_conv_transpose_kernels(s, in, true, 0);
  const ConvResults expected = run_conv_transpose_reference(s, in, true);
  const auto nan_count = [](const std::vector<float>& v) {
    return std::count_if(v.begin(), v.end(), [](float f) { return std::isnan(f); });
  };
  EXPECT_EQ(nan_count(actual.y), 7 * 4);           // its 2x2 block in every output channel
  EXPECT_EQ(nan_count(actual.dx), 5);              // input pixel (5, 0) of image 0, every channel
  EXPECT_EQ(nan_count(actual.dw), 7 * 4 + 5 - 1);  // w[4, :, :, :] and w[:, 6, 1, 0]
  EXPECT_EQ(nan_count(actual.db), 1);
  EXPECT_TRUE(matches_reference("y", actual.y, expected.y, 6));
  EXPECT_TRUE(matches_reference("dx", actual.dx, expected.dx, 28));
  EXPECT_TRUE(matches_reference("dw", actual.dw, expected.dw, 60));
  EXPECT_TRUE(matches_reference("db", actual.db, expected.db, 240));
}

TEST(ConvTranspose2dKernelsDeterminism, SameBitsForEveryRunAndThreadCount) {
  const cuda::ConvTranspose2dShape s{2, 40, 20, 16, 8};
  const ConvTransposeTensors in = conv_transpose_inputs(s, 13);
  const ConvResults first = run_conv_transpose_kernels(s, in, true, 0);
  const int threads = omp_get_max_threads();
  for (const int t : {1, 3}) {
    omp_set_num_threads(t);
    const ConvResults again = run_conv_transpose_kernels(s, in, true, 0);
    EXPECT_TRUE(same_bits(again.y, first.y)) << t << " threads";
    EXPECT_TRUE(same_bits(again.dx, first.dx)) << t << " threads";
    EXPECT_TRUE(same_bits(again.dw, first.dw)) << t << " threads";
    EXPECT_TRUE(same_bits(again.db, first.db)) << t << " threads";
  }
  omp_set_num_threads(threads);
}

TEST(ConvTranspose2dKernelsEdges, EmptyBatchZeroesTheParameterGradients) {
  const cuda::ConvTranspose2dShape s{0, 4, 3, 3, 2};
  GuardedDeviceArray x(0, 0), dy(0, 0);
  GuardedDeviceArray dw(random_values(4 * 2 * 4, 2), 0), db(random_values(2, 3), 0);
  ASSERT_EQ(cuda::conv_transpose2d_backward_weights_workspace(s), 0u);
  cuda::conv_transpose2d_backward_weights(x.data(), dy.data(), dw.data(), db.data(), s, nullptr, 0,
                                          nullptr);
  EXPECT_TRUE(same_bits(dw.download(), std::vector<float>(4 * 2 * 4, 0.0f)));
  EXPECT_TRUE(same_bits(db.download(), std::vector<float>(2, 0.0f)));
}

TEST(ConvTranspose2dKernelsArguments, LaunchersSayWhatIsWrong) {
  DeviceBuffer<float> x(24), w(24), y(96);
  const std::string empty_image = error_message([&] {
    cuda::conv_transpose2d_forward(x.data(), w.data(), nullptr, y.data(), {1, 2, 0, 3, 3}, nullptr);
  });
  EXPECT_NE(empty_image.find("conv_transpose2d_forward: the input must be at least 1x1 (H x W), "
                             "got 0x3"),
            std::string::npos)
      << empty_image;
  const std::string null_dx = error_message([&] {
    cuda::conv_transpose2d_backward_data(y.data(), w.data(), nullptr, {1, 2, 4, 3, 3}, nullptr);
  });
  EXPECT_NE(null_dx.find("conv_transpose2d_backward_data: dx is null but must point to 24 floats"),
            std::string::npos)
      << null_dx;
  const std::string aliased = error_message([&] {
    cuda::conv_transpose2d_forward(y.data(), w.data(), nullptr, y.data() + 4, {1, 2, 2, 2, 3},
                                   nullptr);
  });
  EXPECT_NE(aliased.find("conv_transpose2d_forward: y (48 floats at"), std::string::npos)
      << aliased;
  EXPECT_NE(aliased.find("overlap"), std::string::npos) << aliased;
}

// ---- FastDivmod ----
// A device-side helper, tested on the host through the emulation (test_kernels_conv_gpu, built
// by the host compiler against the nvcc kernels, cannot include it).
#ifdef PILLARSEG_CUDA_EMULATION
TEST(FastDivmod, ExactForEveryDivisorAndDividendRange) {
  constexpr std::int64_t kMaxInt = std::numeric_limits<int>::max();
  std::vector<std::int64_t> divisors;
  for (std::int64_t d = 1; d <= 300; ++d) divisors.push_back(d);
  for (const std::int64_t d : {1023, 1024, 1025, 65535, 65536, 65537, 250000, 500000, 1 << 30,
                               (1 << 30) + 1, std::numeric_limits<int>::max()}) {
    divisors.push_back(d);
  }
  Rng rng(5);
  for (const std::int64_t d : divisors) {
    const cuda::gemm::FastDivmod fast(static_cast<int>(d));
    // Around 0, d and 2d, around the largest multiple of d, at the top of the range (where the
    // rounding error of the multiplier is largest), and random.
    const std::int64_t top_multiple = kMaxInt / d * d;
    std::vector<std::int64_t> dividends = {
        0,           1,      d - 1, d, d + 1, 2 * d - 1, 2 * d, top_multiple - 1, top_multiple,
        kMaxInt - 1, kMaxInt};
    for (int i = 0; i < 200; ++i) {
      dividends.push_back(static_cast<std::int64_t>(rng.uniform_int(std::uint64_t{1} << 31)));
    }
    for (const std::int64_t n : dividends) {
      if (n < 0 || n > kMaxInt) continue;
      int q, r;
      fast.divmod(static_cast<int>(n), q, r);
      ASSERT_EQ(q, n / d) << n << " / " << d;
      ASSERT_EQ(r, n % d) << n << " % " << d;
    }
  }
}

#endif  // PILLARSEG_CUDA_EMULATION

}  // namespace
