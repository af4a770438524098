// host/ AdamW step, gradient norm and clipping, lr / momentum schedules: two Adam steps worked by
// hand, clipping to exactly max_norm, one-cycle values at the start, the peak and the end.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <functional>
#include <limits>
#include <span>
#include <string>
#include <type_traits>
#include <vector>

#include "core/error.hpp"
#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "host/adam.hpp"
#include "host/lr_schedule.hpp"

using namespace pillarseg;
using namespace pillarseg::host;
using ::testing::HasSubstr;

namespace {

std::string error_message(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

}  // namespace

// ---------------------------------------------------------------- Adam

template <class T>
class HostAdam : public ::testing::Test {};
using ScalarTypes = ::testing::Types<float, double>;
TYPED_TEST_SUITE(HostAdam, ScalarTypes);

TYPED_TEST(HostAdam, TwoStepsByHand) {
  using T = TypeParam;
  const double tol = std::is_same_v<T, float> ? 2e-6 : 1e-13;
  const AdamOptions options{
      .lr = 0.1, .beta1 = 0.9, .beta2 = 0.999, .eps = 1e-8, .weight_decay = 0.01};
  std::vector<T> params = {1, -2}, m = {0, 0}, v = {0, 0};

  // Step 1, g = (0.5, -1): decay p *= 1 - 0.1 * 0.01 -> (0.999, -1.998);
  // m = 0.1 g = (0.05, -0.1), v = 0.001 g^2 = (0.00025, 0.001);
  // mhat = m / 0.1 = g, vhat = v / 0.001 = g^2, so the step is lr * g / (|g| + eps).
  const std::vector<T> g1 = {0.5, -1};
  adam_step<T>(params, g1, m, v, 1, options);
  EXPECT_NEAR(m[0], 0.05, tol);
  EXPECT_NEAR(m[1], -0.1, tol);
  EXPECT_NEAR(v[0], 0.00025, tol);
  EXPECT_NEAR(v[1], 0.001, tol);
  const double p1_0 = 0.999 - 0.1 * 0.5 / (0.5 + 1e-8);
  const double p1_1 = -1.998 + 0.1 * 1 / (1 + 1e-8);
  EXPECT_NEAR(params[0], p1_0, tol);  // 0.899
  EXPECT_NEAR(params[1], p1_1, tol);  // -1.898
  EXPECT_NEAR(p1_0, 0.899, 1e-8);

  // Step 2, g = (0.1, 0.2): m = 0.9 m + 0.1 g = (0.055, -0.07);
  // v = 0.999 v + 0.001 g^2 = (0.00025975, 0.001039); bias corrections 1 - 0.9^2 = 0.19 and
  // 1 - 0.999^2 = 0.001999.
  const std::vector<T> g2 = {0.1, 0.2};
  adam_step<T>(params, g2, m, v, 2, options);
  EXPECT_NEAR(m[0], 0.055, tol);
  EXPECT_NEAR(m[1], -0.07, tol);
  EXPECT_NEAR(v[0], 0.00025975, tol);
  EXPECT_NEAR(v[1], 0.001039, tol);
  const double p2_0 =
      p1_0 * 0.999 - 0.1 * (0.055 / 0.19) / (std::sqrt(0.00025975 / 0.001999) + 1e-8);
  const double p2_1 = p1_1 * 0.999 - 0.1 * (-0.07 / 0.19) / (std::sqrt(0.001039 / 0.001999) + 1e-8);
  EXPECT_NEAR(params[0], p2_0, tol);  // 0.8981010 - 0.0803041 = 0.8177969
  EXPECT_NEAR(params[1], p2_1, tol);  // -1.8961020 + 0.0511026 = -1.8449994
  EXPECT_NEAR(p2_0, 0.8177969, 1e-7);
  EXPECT_NEAR(p2_1, -1.8449994, 1e-7);
}

TYPED_TEST(HostAdam, ZeroGradientWithoutDecayKeepsParameters) {
  using T = TypeParam;
  std::vector<T> params = {0.5, -3, 7}, m = {0, 0, 0}, v = {0, 0, 0};
  const std::vector<T> zero = {0, 0, 0};
  for (int64_t step = 1; step <= 3; ++step) adam_step<T>(params, zero, m, v, step, {.weight_decay = 0});
  EXPECT_EQ(params, (std::vector<T>{0.5, -3, 7}));
}

// The threads split the arrays at addresses aligned alike in all three destinations (else one
// pass): every element updated once, with the bits of one pass, for any thread count and offset.
TYPED_TEST(HostAdam, AnyThreadCountGivesTheBitsOfOnePass) {
  using T = TypeParam;
  const size_t n = 1237;
  Rng rng(11);
  std::vector<T> init(4 * n);
  for (T& x : init) x = static_cast<T>(rng.normal());
  const AdamOptions options{
      .lr = 0.003, .beta1 = 0.9, .beta2 = 0.999, .eps = 1e-8, .weight_decay = 0.01};
  // p, m, v at element offsets (op, om, ov) past 64-byte boundaries of one buffer each.
  const auto run = [&](int threads, size_t op, size_t om, size_t ov) {
    const ScopedThreads scoped(threads);
    struct Aligned {
      std::vector<T> storage;
      T* at(size_t offset) {
        const auto address = reinterpret_cast<std::uintptr_t>(storage.data());
        return storage.data() + (64 - address % 64) % 64 / sizeof(T) + offset;
      }
    } buffers[3];
    for (Aligned& b : buffers) b.storage.assign(n + 64, T(0));
    const std::span<T> p(buffers[0].at(op), n), m(buffers[1].at(om), n), v(buffers[2].at(ov), n);
    std::copy_n(init.begin(), n, p.begin());
    std::copy_n(init.begin() + n, n, m.begin());
    for (size_t i = 0; i < n; ++i) v[i] = init[2 * n + i] * init[2 * n + i];
    const std::span<const T> g(init.data() + 3 * n, n);
    for (int64_t step = 1; step <= 3; ++step) adam_step<T>(p, g, m, v, step, options);
    std::vector<T> out(p.begin(), p.end());
    out.insert(out.end(), m.begin(), m.end());
    out.insert(out.end(), v.begin(), v.end());
    return out;
  };
  for (const auto& [op, om, ov] : {std::array<size_t, 3>{0, 0, 0}, {3, 3, 3}, {1, 2, 3}}) {
    const std::vector<T> one = run(1, op, om, ov);
    for (int threads : {2, 3, 7}) {
      const std::vector<T> many = run(threads, op, om, ov);
      ASSERT_EQ(many.size(), one.size());
      for (size_t i = 0; i < one.size(); ++i)
        ASSERT_EQ(std::memcmp(&many[i], &one[i], sizeof(T)), 0)
            << threads << " threads, offsets " << op << " " << om << " " << ov << ", element " << i;
    }
  }
}

TEST(HostAdamErrors, RejectsBadArguments) {
  std::vector<float> params(3), grads(3), m(3), v(2);
  EXPECT_THAT(error_message([&] { adam_step<float>(params, grads, m, v, 1, {}); }),
              HasSubstr("of one length, given 3, 3, 3, 2"));
  v.resize(3);
  EXPECT_THAT(error_message([&] { adam_step<float>(params, grads, m, v, 0, {}); }),
              HasSubstr("expected step >= 1"));
  EXPECT_THAT(error_message([&] { adam_step<float>(params, grads, m, v, 1, {.beta1 = 1}); }),
              HasSubstr("expected beta1, beta2 in [0, 1)"));
}

// ---------------------------------------------------------------- gradient norm and clipping

TEST(HostGradNorm, NormOverAllArraysAndClipToExactlyMaxNorm) {
  std::vector<double> a = {3, 4}, b = {12};
  const std::vector<std::span<double>> grads = {a, b};
  EXPECT_DOUBLE_EQ(grad_norm<double>(grads), 13.0);

  EXPECT_DOUBLE_EQ(clip_grad_norm<double>(grads, 20.0), 13.0);  // below max_norm: unchanged
  EXPECT_EQ(a, (std::vector<double>{3, 4}));
  EXPECT_EQ(b, (std::vector<double>{12}));

  EXPECT_DOUBLE_EQ(clip_grad_norm<double>(grads, 6.5), 13.0);  // returns the norm before
  const double scale = 6.5 / (13 + 1e-6);
  EXPECT_DOUBLE_EQ(a[0], 3 * scale);
  EXPECT_DOUBLE_EQ(b[0], 12 * scale);
  EXPECT_NEAR(grad_norm<double>(grads), 6.5, 1e-6);

  std::vector<float> f = {1e20f, 1e20f};  // squares overflow float, not the double sum
  const std::vector<std::span<float>> float_grads = {f};
  EXPECT_DOUBLE_EQ(clip_grad_norm<float>(float_grads, 10.0), std::sqrt(2.0) * 1e20f);
  EXPECT_NEAR(grad_norm<float>(float_grads), 10.0, 1e-5);

  EXPECT_EQ(grad_norm<double>({}), 0.0);
}

// The one clipping rule (PyTorch's clip_grad_norm_), which the trainer applies to the backend's
// gradients too: max_norm / (norm + 1e-6) where below 1; a norm equal to max_norm is scaled by
// just under 1, one within 1e-6 below it is not scaled.
TEST(HostGradNorm, ClipCoefficientByHand) {
  EXPECT_DOUBLE_EQ(clip_coefficient(13.0, 6.5), 6.5 / (13.0 + 1e-6));
  EXPECT_EQ(clip_coefficient(5.0, 10.0), 1.0);
  EXPECT_EQ(clip_coefficient(0.0, 10.0), 1.0);
  EXPECT_DOUBLE_EQ(clip_coefficient(10.0, 10.0), 10.0 / (10.0 + 1e-6));
  EXPECT_LT(clip_coefficient(10.0, 10.0), 1.0);
  EXPECT_EQ(clip_coefficient(10.0 - 2e-6, 10.0), 1.0);
  EXPECT_EQ(clip_coefficient(std::numeric_limits<double>::quiet_NaN(), 1.0), 1.0);  // left as it is
}

TEST(HostGradNorm, NonFiniteNormLeavesGradients) {
  std::vector<double> a = {1, std::numeric_limits<double>::quiet_NaN()};
  const std::vector<std::span<double>> grads = {a};
  EXPECT_TRUE(std::isnan(clip_grad_norm<double>(grads, 1.0)));
  EXPECT_EQ(a[0], 1.0);
  EXPECT_THAT(error_message([&] { clip_grad_norm<double>(grads, 0.0); }),
              HasSubstr("expected max_norm > 0"));
}

// ---------------------------------------------------------------- schedules

TEST(HostLrSchedule, OneCycleStartPeakAndEnd) {
  const LrScheduleOptions options{.lr_max = 1e-3, .total_steps = 100};
  auto at = [&](int64_t step) { return lr_schedule_at(options, step); };
  EXPECT_NEAR(at(0).lr, 1e-4, 1e-18);  // lr_max / div_factor
  EXPECT_NEAR(at(0).beta1, 0.95, 1e-15);
  EXPECT_NEAR(at(20).lr, (1e-4 + 1e-3) / 2, 1e-18);  // halfway up the cosine
  EXPECT_NEAR(at(20).beta1, 0.90, 1e-15);
  EXPECT_NEAR(at(40).lr, 1e-3, 1e-18);  // pct_start: the peak
  EXPECT_NEAR(at(40).beta1, 0.85, 1e-15);
  EXPECT_NEAR(at(70).lr, (1e-3 + 1e-8) / 2, 1e-18);
  EXPECT_NEAR(at(70).beta1, 0.90, 1e-15);
  EXPECT_NEAR(at(100).lr, 1e-8, 1e-18);  // lr_max / div_factor / 1e4
  EXPECT_NEAR(at(100).beta1, 0.95, 1e-15);
  EXPECT_NEAR(at(99).lr, cos_anneal(1e-3, 1e-8, 59.0 / 60), 1e-18);
  for (int64_t s = 1; s <= 100; ++s) {
    if (s <= 40) {
      EXPECT_GT(at(s).lr, at(s - 1).lr) << s;
      EXPECT_LT(at(s).beta1, at(s - 1).beta1) << s;
    } else {
      EXPECT_LT(at(s).lr, at(s - 1).lr) << s;
      EXPECT_GT(at(s).beta1, at(s - 1).beta1) << s;
    }
  }
}

TEST(HostLrSchedule, PeakStepIsFloorOfTotalTimesPctStart) {
  // OpenPCDet: int(7 * 0.4) = 2.
  const LrScheduleOptions options{.lr_max = 1.0, .total_steps = 7};
  EXPECT_NEAR(lr_schedule_at(options, 1).lr, cos_anneal(0.1, 1.0, 0.5), 1e-15);
  EXPECT_DOUBLE_EQ(lr_schedule_at(options, 2).lr, 1.0);
  EXPECT_NEAR(lr_schedule_at(options, 4).lr, cos_anneal(1.0, 1e-5, 2.0 / 5), 1e-15);
  // One step: no warm-up at all.
  EXPECT_DOUBLE_EQ(lr_schedule_at({.lr_max = 1.0, .total_steps = 1}, 0).lr, 1.0);
}

TEST(HostLrSchedule, CosAnnealEndsAndConstantSchedule) {
  EXPECT_DOUBLE_EQ(cos_anneal(3, 1, 0), 3);
  EXPECT_DOUBLE_EQ(cos_anneal(3, 1, 1), 1);
  EXPECT_DOUBLE_EQ(cos_anneal(3, 1, 0.5), 2);
  const LrScheduleOptions constant{.kind = LrScheduleKind::kConstant, .lr_max = 2e-3};
  for (int64_t s : {0, 1, 1000000}) {
    EXPECT_EQ(lr_schedule_at(constant, s).lr, 2e-3);
    EXPECT_EQ(lr_schedule_at(constant, s).beta1, 0.9);
  }
}

TEST(HostLrSchedule, RejectsBadArguments) {
  const LrScheduleOptions options{.total_steps = 10};
  EXPECT_THAT(error_message([&] { lr_schedule_at(options, 11); }),
              HasSubstr("step 11 is past the end of the 10-step cycle"));
  EXPECT_THAT(error_message([&] { lr_schedule_at(options, -1); }), HasSubstr("step >= 0"));
  EXPECT_THAT(error_message([&] { lr_schedule_at({.total_steps = 0}, 0); }),
              HasSubstr("total_steps >= 1"));
  EXPECT_THAT(error_message([&] { lr_schedule_at({.total_steps = 10, .pct_start = 1}, 0); }),
              HasSubstr("pct_start in (0, 1)"));
}
