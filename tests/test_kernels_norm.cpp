// kernels/batchnorm.cu and kernels/pfn.cu on the CUDA emulation, against the CPU reference ops
// host/batchnorm.hpp and host/pfn.hpp on the same inputs: planes that are and are not multiples
// of 4 (float4 and scalar paths) and of the 4096-value chunk, misaligned arrays, C = 1, S = 1,
// an empty batch, 0 and 1 pillar, channel counts that are not multiples of the 32-channel tile,
// NaN and Inf inputs, a large mean against a small spread, in-place use, guard words after every
// output and workspace, bitwise determinism across runs and thread counts, and argument checks;
// synchronised BatchNorm with its sums over the replicas on the host and on the device.
// Backward passes get the reference forward's saved statistics (and ReLU output and max slots),
// so each kernel is compared on identical inputs.
#include <gtest/gtest.h>
#include <omp.h>

#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "host/batchnorm.hpp"
#include "host/pfn.hpp"
#include "kernels/batchnorm.cuh"
#include "kernels/cuda_handles.hpp"
#include "kernels/pfn.cuh"
#include "kernels/replica_sum.cuh"
#include "tests/kernel_test_helpers.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using kernel_test::GuardedArray;
using kernel_test::normal_tensor;
using kernel_test::normal_values;
using kernel_test::same_bits;

namespace {

::testing::AssertionResult close(const std::vector<float>& actual, const Tensor<float>& expected,
                                 double atol, double rtol) {
  if (static_cast<std::int64_t>(actual.size()) != expected.numel()) {
    return ::testing::AssertionFailure()
           << "size " << actual.size() << " != expected " << expected.numel();
  }
  return test::all_close(actual.data(), expected.data(), expected.numel(), atol, rtol);
}

// ---------------------------------------------------------------------------------------------
// BatchNorm

constexpr float kEps = 1e-5f;
constexpr float kMomentum = 0.1f;
const host::BatchNormOptions kHostOptions{kEps, kMomentum};

struct BatchNormInputs {
  Tensor<float> x, gamma, beta, running_mean, running_var;
};

BatchNormInputs batchnorm_inputs(const Shape& shape, std::uint64_t seed, double spread = 2.0,
                                 double mean = 0.5) {
  const Shape channels{shape[1]};
  BatchNormInputs in{normal_tensor(shape, seed, spread, mean),
                     normal_tensor(channels, seed + 1, 0.5, 1.0),
                     normal_tensor(channels, seed + 2, 0.3), normal_tensor(channels, seed + 3, 0.2),
                     normal_tensor(channels, seed + 4, 0.1, 1.0)};
  for (float& v : in.running_var) v = std::abs(v);
  return in;
}

cuda::PlanarShape planar(const Shape& shape) {
  return {shape[0], shape[1], shape[2] * shape[3]};
}

// The device training forward: outputs and running statistics as host tensors.
struct DeviceTrain {
  std::vector<float> y, running_mean, running_var, save_mean, save_inv_std;
};

DeviceTrain device_train(const BatchNormInputs& in, bool relu, std::int64_t offset,
                         ReplicaSum* replicas = nullptr) {
  const Shape& shape = in.x.shape();
  const std::int64_t n = in.x.numel(), c = shape[1];
  GuardedArray<float> x(in.x, offset), y(n, offset), gamma(in.gamma), beta(in.beta);
  GuardedArray<float> running_mean(in.running_mean), running_var(in.running_var);
  GuardedArray<float> save_mean(c), save_inv_std(c);
  GuardedArray<double> workspace(cuda::batchnorm_workspace_doubles(planar(shape)));
  cuda::batchnorm_forward_train(x.data(), planar(shape), gamma.data(), beta.data(), kEps, kMomentum,
                                running_mean.data(), running_var.data(), relu, y.data(),
                                save_mean.data(), save_inv_std.data(), workspace.data(), nullptr,
                                replicas);
  for (const GuardedArray<float>* a :
       {&y, &running_mean, &running_var, &save_mean, &save_inv_std}) {
    EXPECT_TRUE(a->guards_intact());
  }
  EXPECT_TRUE(workspace.guards_intact()) << "batchnorm_workspace_doubles is too small";
  EXPECT_TRUE(same_bits(x.download(), in.x)) << "the input must not change";
  return {y.download(), running_mean.download(), running_var.download(), save_mean.download(),
          save_inv_std.download()};
}

struct HostTrain {
  Tensor<float> y, running_mean, running_var;
  host::BatchNormSaved<float> saved;
};

HostTrain host_train(const BatchNormInputs& in, bool relu) {
  HostTrain out{Tensor<float>(), in.running_mean, in.running_var, {}};
  std::int64_t batches = 0;
  if (relu) {
    host::batchnorm_relu_forward_train(in.x, in.gamma, in.beta, kHostOptions, out.running_mean,
                                       out.running_var, batches, out.y, out.saved);
  } else {
    host::batchnorm_forward_train(in.x, in.gamma, in.beta, kHostOptions, out.running_mean,
                                  out.running_var, batches, out.y, out.saved);
  }
  return out;
}

void expect_train_matches(const BatchNormInputs& in, bool relu, std::int64_t offset) {
  const HostTrain expected = host_train(in, relu);
  const DeviceTrain actual = device_train(in, relu, offset);
  EXPECT_TRUE(close(actual.y, expected.y, 1e-5, 1e-5)) << "y";
  EXPECT_TRUE(close(actual.save_mean, expected.saved.mean, 1e-6, 1e-6)) << "save_mean";
  EXPECT_TRUE(close(actual.save_inv_std, expected.saved.inv_std, 0.0, 1e-6)) << "save_inv_std";
  EXPECT_TRUE(close(actual.running_mean, expected.running_mean, 1e-7, 1e-6)) << "running_mean";
  EXPECT_TRUE(close(actual.running_var, expected.running_var, 1e-7, 1e-6)) << "running_var";
}

struct BackwardResult {
  std::vector<float> dx, dgamma, dbeta;
};

// The device backward on the host forward's saved statistics and output.
BackwardResult device_backward(const BatchNormInputs& in, const HostTrain& forward,
                               const Tensor<float>& dy_values, bool relu, std::int64_t offset,
                               ReplicaSum* replicas = nullptr) {
  const Shape& shape = in.x.shape();
  const std::int64_t n = in.x.numel(), c = shape[1];
  GuardedArray<float> x(in.x, offset), y(forward.y, offset), dy(dy_values, offset), dx(n, offset);
  GuardedArray<float> gamma(in.gamma), mean(forward.saved.mean), inv_std(forward.saved.inv_std);
  GuardedArray<float> dgamma(c), dbeta(c);
  GuardedArray<double> workspace(cuda::batchnorm_workspace_doubles(planar(shape)));
  cuda::batchnorm_backward(dy.data(), x.data(), relu ? y.data() : nullptr, planar(shape),
                           gamma.data(), mean.data(), inv_std.data(), dx.data(), dgamma.data(),
                           dbeta.data(), workspace.data(), nullptr, replicas);
  EXPECT_TRUE(dx.guards_intact());
  EXPECT_TRUE(dgamma.guards_intact());
  EXPECT_TRUE(dbeta.guards_intact());
  EXPECT_TRUE(workspace.guards_intact()) << "batchnorm_workspace_doubles is too small";
  return {dx.download(), dgamma.download(), dbeta.download()};
}

void expect_backward_matches(const BatchNormInputs& in, bool relu, std::int64_t offset,
                             std::uint64_t seed) {
  const HostTrain forward = host_train(in, relu);
  const Tensor<float> dy = normal_tensor(in.x.shape(), seed);
  Tensor<float> dx, dgamma, dbeta;
  if (relu) {
    host::batchnorm_relu_backward(dy, in.x, forward.y, in.gamma, forward.saved, dx, dgamma, dbeta);
  } else {
    host::batchnorm_backward(dy, in.x, in.gamma, forward.saved, dx, dgamma, dbeta);
  }
  const BackwardResult actual = device_backward(in, forward, dy, relu, offset);
  EXPECT_TRUE(close(actual.dx, dx, 1e-5, 1e-5)) << "dx";
  EXPECT_TRUE(close(actual.dgamma, dgamma, 1e-5, 1e-6)) << "dgamma";
  EXPECT_TRUE(close(actual.dbeta, dbeta, 1e-5, 1e-6)) << "dbeta";
}

struct BatchNormCase {
  Shape shape;
  std::int64_t offset;  // floats past a 16-byte boundary
};

const std::vector<BatchNormCase> kBatchNormCases = {
    {{2, 3, 5, 7}, 0},    // S = 35: scalar path, one partial chunk
    {{1, 1, 64, 64}, 0},  // C = 1, S = 4096: float4, exactly one chunk
    {{2, 4, 72, 64}, 0},  // S = 4608: float4, a full and a partial chunk per plane
    {{2, 5, 67, 65}, 0},  // S = 4355: scalar, two chunks
    {{2, 4, 72, 64}, 1},  // misaligned arrays: the scalar path on a float4-sized plane
    {{3, 2, 1, 1}, 0},    // S = 1: one value per plane
    {{1, 33, 3, 4}, 0},   // C = 33: a finalize block with one channel
};

std::string case_name(const BatchNormCase& c, bool relu) {
  return shape_str(c.shape) + " offset " + std::to_string(c.offset) + (relu ? " relu" : "");
}

}  // namespace

TEST(BatchNormKernels, TrainingForwardMatchesTheReference) {
  std::uint64_t seed = 100;
  for (const BatchNormCase& c : kBatchNormCases) {
    for (const bool relu : {false, true}) {
      SCOPED_TRACE(case_name(c, relu));
      expect_train_matches(batchnorm_inputs(c.shape, seed++), relu, c.offset);
    }
  }
}

TEST(BatchNormKernels, EvaluationForwardMatchesTheReference) {
  std::uint64_t seed = 200;
  for (const BatchNormCase& c : kBatchNormCases) {
    for (const bool relu : {false, true}) {
      SCOPED_TRACE(case_name(c, relu));
      const BatchNormInputs in = batchnorm_inputs(c.shape, seed++);
      Tensor<float> expected;
      if (relu) {
        host::batchnorm_relu_forward_eval(in.x, in.gamma, in.beta, in.running_mean, in.running_var,
                                          kHostOptions, expected);
      } else {
        host::batchnorm_forward_eval(in.x, in.gamma, in.beta, in.running_mean, in.running_var,
                                     kHostOptions, expected);
      }
      GuardedArray<float> x(in.x, c.offset), y(in.x.numel(), c.offset);
      GuardedArray<float> gamma(in.gamma), beta(in.beta), mean(in.running_mean),
          var(in.running_var);
      cuda::batchnorm_forward_eval(x.data(), planar(c.shape), gamma.data(), beta.data(),
                                   mean.data(), var.data(), kEps, relu, y.data(), nullptr);
      EXPECT_TRUE(close(y.download(), expected, 1e-6, 1e-6));
      EXPECT_TRUE(y.guards_intact());
    }
  }
}

TEST(BatchNormKernels, BackwardMatchesTheReference) {
  std::uint64_t seed = 300;
  for (const BatchNormCase& c : kBatchNormCases) {
    for (const bool relu : {false, true}) {
      SCOPED_TRACE(case_name(c, relu));
      expect_backward_matches(batchnorm_inputs(c.shape, seed), relu, c.offset, seed + 50);
      ++seed;
    }
  }
}

TEST(BatchNormKernels, LargeMeanAgainstASmallSpread) {
  // Values near 1e4 with a spread of 0.01: E[x^2] - E[x]^2 would lose the variance to
  // cancellation (relative error ~1e-4 in double); the shifted sums keep it.
  const BatchNormInputs in = batchnorm_inputs({2, 3, 33, 40}, 400, 0.01, 1e4);
  expect_train_matches(in, true, 0);
}

TEST(BatchNormKernels, NanAndInfReachTheirChannelOnly) {
  BatchNormInputs in = batchnorm_inputs({2, 3, 9, 8}, 500);
  in.x(1, 0, 4, 5) = std::numeric_limits<float>::quiet_NaN();  // channel 0: NaN statistics
  in.x(0, 1, 0, 0) = std::numeric_limits<float>::quiet_NaN();  // channel 1, its first value
  in.x(1, 2, 8, 7) = std::numeric_limits<float>::infinity();   // channel 2: mean Inf, var NaN
  for (const bool relu : {false, true}) {
    SCOPED_TRACE(relu ? "relu" : "plain");
    expect_train_matches(in, relu, 0);
    const DeviceTrain actual = device_train(in, relu, 0);
    EXPECT_TRUE(std::isnan(actual.y[0])) << "channel 0 is NaN throughout";
    EXPECT_EQ(actual.save_mean[2], std::numeric_limits<float>::infinity());
    EXPECT_TRUE(std::isnan(actual.running_var[2]));
  }
  // Only the NaN-free channel passes the backward's check against the reference.
  BatchNormInputs finite = batchnorm_inputs({2, 1, 9, 8}, 501);
  expect_backward_matches(finite, true, 0, 502);
}

TEST(BatchNormKernels, EmptyBatchLeavesTheRunningStatistics) {
  const BatchNormInputs in = batchnorm_inputs({0, 4, 5, 5}, 600);
  const HostTrain expected = host_train(in, true);
  const DeviceTrain actual = device_train(in, true, 0);
  EXPECT_TRUE(same_bits(actual.running_mean, in.running_mean));
  EXPECT_TRUE(same_bits(actual.running_var, in.running_var));
  EXPECT_TRUE(close(actual.save_mean, expected.saved.mean, 0.0, 0.0));
  EXPECT_TRUE(close(actual.save_inv_std, expected.saved.inv_std, 0.0, 1e-7));
  EXPECT_EQ(actual.save_inv_std[0], static_cast<float>(1.0 / std::sqrt(double{kEps})));
}

TEST(BatchNormKernels, InPlace) {
  const BatchNormInputs in = batchnorm_inputs({2, 3, 16, 20}, 700);
  const Shape& shape = in.x.shape();
  const HostTrain expected = host_train(in, true);
  GuardedArray<float> x(in.x), gamma(in.gamma), beta(in.beta), mean(in.running_mean),
      var(in.running_var), save_mean(3), save_inv_std(3);
  GuardedArray<double> workspace(cuda::batchnorm_workspace_doubles(planar(shape)));
  cuda::batchnorm_forward_train(x.data(), planar(shape), gamma.data(), beta.data(), kEps, kMomentum,
                                mean.data(), var.data(), true, x.data(), save_mean.data(),
                                save_inv_std.data(), workspace.data(), nullptr);
  EXPECT_TRUE(close(x.download(), expected.y, 1e-5, 1e-5));

  // dx in place of dy.
  const Tensor<float> dy_values = normal_tensor(shape, 701);
  Tensor<float> dx, dgamma, dbeta;
  host::batchnorm_relu_backward(dy_values, in.x, expected.y, in.gamma, expected.saved, dx, dgamma,
                                dbeta);
  GuardedArray<float> input(in.x), y(expected.y), dy(dy_values), saved_mean(expected.saved.mean),
      saved_inv_std(expected.saved.inv_std), device_dgamma(3), device_dbeta(3);
  cuda::batchnorm_backward(dy.data(), input.data(), y.data(), planar(shape), gamma.data(),
                           saved_mean.data(), saved_inv_std.data(), dy.data(), device_dgamma.data(),
                           device_dbeta.data(), workspace.data(), nullptr);
  EXPECT_TRUE(close(dy.download(), dx, 1e-5, 1e-5));
  EXPECT_TRUE(close(device_dgamma.download(), dgamma, 1e-5, 1e-6));
}

TEST(BatchNormKernels, SameBitsForEveryRunAndThreadCount) {
  const BatchNormInputs in = batchnorm_inputs({2, 4, 72, 64}, 800);
  const HostTrain forward = host_train(in, true);
  const Tensor<float> dy = normal_tensor(in.x.shape(), 801);
  const DeviceTrain reference = device_train(in, true, 0);
  const BackwardResult reference_backward = device_backward(in, forward, dy, true, 0);
  const int threads = omp_get_max_threads();
  for (const int t : {1, 3}) {
    omp_set_num_threads(t);
    const DeviceTrain again = device_train(in, true, 0);
    EXPECT_TRUE(same_bits(again.y, reference.y)) << t << " threads";
    EXPECT_TRUE(same_bits(again.save_mean, reference.save_mean));
    EXPECT_TRUE(same_bits(again.save_inv_std, reference.save_inv_std));
    EXPECT_TRUE(same_bits(again.running_var, reference.running_var));
    const BackwardResult backward = device_backward(in, forward, dy, true, 0);
    EXPECT_TRUE(same_bits(backward.dx, reference_backward.dx));
    EXPECT_TRUE(same_bits(backward.dgamma, reference_backward.dgamma));
    EXPECT_TRUE(same_bits(backward.dbeta, reference_backward.dbeta));
  }
  omp_set_num_threads(threads);
}

TEST(BatchNormKernels, LaunchersCheckTheirArguments) {
  cuda::DeviceBuffer<float> buffer(16);
  cuda::DeviceBuffer<double> workspace(64);
  float* p = buffer.data();
  const std::string one_value = kernel_test::error_message([&] {
    cuda::batchnorm_forward_train(p, {1, 2, 1}, p, p, kEps, kMomentum, p, p, true, p, p, p,
                                  workspace.data(), nullptr);
  });
  EXPECT_NE(one_value.find("expected more than 1 value per channel when training"),
            std::string::npos)
      << one_value;
  const std::string no_channels = kernel_test::error_message([&] {
    cuda::batchnorm_forward_eval(p, {1, 0, 4}, p, p, p, p, kEps, false, p, nullptr);
  });
  EXPECT_NE(no_channels.find("expected x of (B, C, S = H * W)"), std::string::npos) << no_channels;
  const std::string bad_eps = kernel_test::error_message([&] {
    cuda::batchnorm_forward_eval(p, {1, 2, 4}, p, p, p, p, 0.0f, false, p, nullptr);
  });
  EXPECT_NE(bad_eps.find("expected eps > 0"), std::string::npos) << bad_eps;
  const std::string no_workspace = kernel_test::error_message([&] {
    cuda::batchnorm_backward(p, p, nullptr, {1, 2, 4}, p, p, p, p, p, p, nullptr, nullptr);
  });
  EXPECT_NE(no_workspace.find("the workspace (8 doubles)"), std::string::npos) << no_workspace;
}

// ---------------------------------------------------------------------------------------------
// PFN

namespace {

constexpr float kPfnEps = 1e-3f;
constexpr float kPfnMomentum = 0.01f;
const host::BatchNormOptions kHostPfnOptions{kPfnEps, kPfnMomentum};

struct PfnInputs {
  Tensor<float> points, weight, gamma, beta, running_mean, running_var;
  cuda::PfnShape shape() const { return {points.dim(0), points.dim(1), weight.dim(0)}; }
};

// Values on a grid of 1/8 (points) and 1/16 (weights): z = points . w is exact in float in any
// order of the sums, so the reference and the kernels see the same z and pick the same max slots.
PfnInputs pfn_inputs(std::int64_t pillars, std::int64_t slots, std::int64_t channels,
                     std::uint64_t seed) {
  Rng rng(seed);
  Tensor<float> points({pillars, slots, cuda::kPfnFeatures});
  for (std::int64_t p = 0; p < pillars; ++p) {
    const auto used =
        static_cast<std::int64_t>(1 + rng.uniform_int(static_cast<std::uint64_t>(slots)));
    for (std::int64_t n = 0; n < used; ++n) {  // the rest are padding: zero rows
      for (std::int64_t d = 0; d < cuda::kPfnFeatures; ++d) {
        points(p, n, d) = static_cast<float>(std::round(rng.normal() * 8.0) / 8.0);
      }
    }
  }
  Tensor<float> weight({channels, cuda::kPfnFeatures});
  for (float& w : weight) w = static_cast<float>(std::round(rng.normal() * 0.3 * 16.0) / 16.0);
  PfnInputs in{points,
               weight,
               normal_tensor({channels}, seed + 1, 0.3, 1.0),
               normal_tensor({channels}, seed + 2, 0.5),
               normal_tensor({channels}, seed + 3, 0.5),
               normal_tensor({channels}, seed + 4, 0.5, 2.0)};
  for (float& v : in.running_var) v = std::abs(v);
  return in;
}

struct PfnDeviceForward {
  std::vector<float> out, running_mean, running_var, save_mean, save_inv_std;
  std::vector<std::int32_t> max_slot;
};

PfnDeviceForward device_pfn_train(const PfnInputs& in, ReplicaSum* replicas = nullptr) {
  const cuda::PfnShape s = in.shape();
  GuardedArray<float> points(in.points), weight(in.weight), gamma(in.gamma), beta(in.beta);
  GuardedArray<float> running_mean(in.running_mean), running_var(in.running_var);
  GuardedArray<float> out(s.pillars * s.channels), save_mean(s.channels), save_inv_std(s.channels);
  GuardedArray<std::int32_t> max_slot(s.pillars * s.channels);
  GuardedArray<double> workspace(cuda::pfn_workspace_doubles(s));
  cuda::pfn_forward_train(points.data(), weight.data(), s, gamma.data(), beta.data(), kPfnEps,
                          kPfnMomentum, running_mean.data(), running_var.data(), out.data(),
                          max_slot.data(), save_mean.data(), save_inv_std.data(), workspace.data(),
                          nullptr, replicas);
  for (const GuardedArray<float>* a :
       {&out, &running_mean, &running_var, &save_mean, &save_inv_std}) {
    EXPECT_TRUE(a->guards_intact());
  }
  EXPECT_TRUE(max_slot.guards_intact());
  EXPECT_TRUE(workspace.guards_intact()) << "pfn_workspace_doubles is too small";
  return {out.download(),       running_mean.download(), running_var.download(),
          save_mean.download(), save_inv_std.download(), max_slot.download()};
}

struct PfnHostForward {
  Tensor<float> out, running_mean, running_var;
  host::PfnSaved<float> saved;
};

PfnHostForward host_pfn_train(const PfnInputs& in) {
  PfnHostForward r{Tensor<float>(), in.running_mean, in.running_var, {}};
  std::int64_t batches = 0;
  host::pfn_forward_train(in.points, in.weight, in.gamma, in.beta, kHostPfnOptions, r.running_mean,
                          r.running_var, batches, r.out, r.saved);
  return r;
}

struct PfnGradients {
  std::vector<float> d_points, d_weight, d_gamma, d_beta;
};

PfnGradients device_pfn_backward(const PfnInputs& in, const PfnHostForward& forward,
                                 const Tensor<float>& d_out_values, bool with_d_points,
                                 ReplicaSum* replicas = nullptr) {
  const cuda::PfnShape s = in.shape();
  GuardedArray<float> points(in.points), weight(in.weight), gamma(in.gamma), d_out(d_out_values);
  GuardedArray<float> save_mean(forward.saved.norm.mean), save_inv_std(forward.saved.norm.inv_std);
  GuardedArray<std::int32_t> max_slot(
      std::vector<std::int32_t>(forward.saved.max_slot.begin(), forward.saved.max_slot.end()));
  GuardedArray<float> d_points(s.rows() * cuda::kPfnFeatures),
      d_weight(s.channels * cuda::kPfnFeatures);
  GuardedArray<float> d_gamma(s.channels), d_beta(s.channels);
  GuardedArray<double> workspace(cuda::pfn_workspace_doubles(s));
  cuda::pfn_backward(d_out.data(), points.data(), weight.data(), s, gamma.data(), save_mean.data(),
                     save_inv_std.data(), max_slot.data(),
                     with_d_points ? d_points.data() : nullptr, d_weight.data(), d_gamma.data(),
                     d_beta.data(), workspace.data(), nullptr, replicas);
  for (const GuardedArray<float>* a : {&d_points, &d_weight, &d_gamma, &d_beta}) {
    EXPECT_TRUE(a->guards_intact());
  }
  EXPECT_TRUE(workspace.guards_intact()) << "pfn_workspace_doubles is too small";
  return {d_points.download(), d_weight.download(), d_gamma.download(), d_beta.download()};
}

struct PfnCase {
  std::int64_t pillars, slots, channels;
};

const std::vector<PfnCase> kPfnCases = {
    {1, 20, 64},    // one pillar
    {37, 20, 64},   // pillars not a multiple of the 8 per block
    {300, 20, 33},  // 6000 rows: several 1024-row blocks; 2 pillar blocks; a 1-channel tile
    {6, 1, 1},      // N = 1, C = 1
    {9, 3, 70},     // three channel tiles, the last partial
};

std::string pfn_case_name(const PfnCase& c) {
  return "P " + std::to_string(c.pillars) + ", N " + std::to_string(c.slots) + ", C " +
         std::to_string(c.channels);
}

}  // namespace

TEST(PfnKernels, TrainingForwardMatchesTheReference) {
  std::uint64_t seed = 1000;
  for (const PfnCase& c : kPfnCases) {
    SCOPED_TRACE(pfn_case_name(c));
    const PfnInputs in = pfn_inputs(c.pillars, c.slots, c.channels, seed++);
    const PfnHostForward expected = host_pfn_train(in);
    const PfnDeviceForward actual = device_pfn_train(in);
    EXPECT_TRUE(close(actual.out, expected.out, 1e-5, 1e-5)) << "out";
    EXPECT_TRUE(same_bits(actual.max_slot, expected.saved.max_slot)) << "max_slot";
    EXPECT_TRUE(close(actual.save_mean, expected.saved.norm.mean, 1e-6, 1e-6)) << "save_mean";
    EXPECT_TRUE(close(actual.save_inv_std, expected.saved.norm.inv_std, 0.0, 1e-6));
    EXPECT_TRUE(close(actual.running_mean, expected.running_mean, 1e-7, 1e-6));
    EXPECT_TRUE(close(actual.running_var, expected.running_var, 1e-7, 1e-6));
  }
}

TEST(PfnKernels, EvaluationForwardMatchesTheReference) {
  std::uint64_t seed = 1100;
  for (const PfnCase& c : kPfnCases) {
    SCOPED_TRACE(pfn_case_name(c));
    const PfnInputs in = pfn_inputs(c.pillars, c.slots, c.channels, seed++);
    Tensor<float> expected;
    host::pfn_forward_eval(in.points, in.weight, in.gamma, in.beta, in.running_mean, in.running_var,
                           kHostPfnOptions, expected);
    const cuda::PfnShape s = in.shape();
    GuardedArray<float> points(in.points), weight(in.weight), gamma(in.gamma), beta(in.beta),
        mean(in.running_mean), var(in.running_var), out(s.pillars * s.channels);
    GuardedArray<std::int32_t> max_slot(s.pillars * s.channels);
    for (const bool with_slots : {false, true}) {
      cuda::pfn_forward_eval(points.data(), weight.data(), s, gamma.data(), beta.data(),
                             mean.data(), var.data(), kPfnEps, out.data(),
                             with_slots ? max_slot.data() : nullptr, nullptr);
      EXPECT_TRUE(close(out.download(), expected, 1e-5, 1e-5));
      EXPECT_TRUE(out.guards_intact());
    }
    // The slots are those of the maxima: -1 exactly where the output is not > 0.
    const std::vector<std::int32_t> slots = max_slot.download();
    for (std::size_t i = 0; i < slots.size(); ++i) {
      EXPECT_EQ(slots[i] >= 0, expected[static_cast<std::int64_t>(i)] > 0.0f) << "output " << i;
      EXPECT_LT(slots[i], c.slots);
    }
  }
}

TEST(PfnKernels, BackwardMatchesTheReference) {
  std::uint64_t seed = 1200;
  for (const PfnCase& c : kPfnCases) {
    SCOPED_TRACE(pfn_case_name(c));
    const PfnInputs in = pfn_inputs(c.pillars, c.slots, c.channels, seed);
    const PfnHostForward forward = host_pfn_train(in);
    const Tensor<float> d_out = normal_tensor({c.pillars, c.channels}, seed + 50);
    ++seed;
    Tensor<float> d_points, d_weight, d_gamma, d_beta;
    host::pfn_backward(d_out, in.points, in.weight, in.gamma, forward.saved, d_points, d_weight,
                       d_gamma, d_beta);
    const PfnGradients actual = device_pfn_backward(in, forward, d_out, true);
    EXPECT_TRUE(close(actual.d_gamma, d_gamma, 1e-5, 1e-5)) << "d_gamma";
    EXPECT_TRUE(close(actual.d_beta, d_beta, 1e-5, 1e-5)) << "d_beta";
    // d_weight sums P * N rows; the reference does it in float (Eigen's product), the kernels
    // in float per 128 rows and then in double.
    EXPECT_LT(kernel_test::normalized_mse(actual.d_weight, kernel_test::to_vector(d_weight)),
              1e-10);
    EXPECT_TRUE(close(actual.d_weight, d_weight, 1e-4, 1e-4)) << "d_weight";
    EXPECT_TRUE(close(actual.d_points, d_points, 1e-5, 1e-4)) << "d_points";
    const PfnGradients without_points = device_pfn_backward(in, forward, d_out, false);
    EXPECT_TRUE(same_bits(without_points.d_weight, actual.d_weight));
  }
}

TEST(PfnKernels, NoPillars) {
  const PfnInputs in = pfn_inputs(0, 20, 64, 1300);
  const PfnHostForward expected = host_pfn_train(in);
  const PfnDeviceForward actual = device_pfn_train(in);
  EXPECT_TRUE(actual.out.empty());
  EXPECT_TRUE(same_bits(actual.running_mean, in.running_mean)) << "no batch to measure";
  EXPECT_TRUE(same_bits(actual.running_var, in.running_var));
  EXPECT_TRUE(close(actual.save_mean, expected.saved.norm.mean, 0.0, 0.0));
  EXPECT_TRUE(close(actual.save_inv_std, expected.saved.norm.inv_std, 0.0, 1e-7));
  const PfnGradients gradients = device_pfn_backward(in, expected, Tensor<float>({0, 64}), true);
  for (const float g : gradients.d_weight) EXPECT_EQ(g, 0.0f);
  for (const float g : gradients.d_gamma) EXPECT_EQ(g, 0.0f);
}

TEST(PfnKernels, NanPointReachesItsPillar) {
  PfnInputs in = pfn_inputs(12, 4, 8, 1400);
  in.points(5, 0, 2) = std::numeric_limits<float>::quiet_NaN();
  // A NaN row makes every channel's statistics NaN: the whole output is NaN, as in PyTorch.
  const PfnHostForward expected = host_pfn_train(in);
  const PfnDeviceForward actual = device_pfn_train(in);
  EXPECT_TRUE(close(actual.out, expected.out, 0.0, 0.0));
  EXPECT_TRUE(std::isnan(actual.out[0]));
  // With the running statistics only pillar 5 sees the NaN; its slot is the NaN's.
  Tensor<float> expected_eval;
  host::pfn_forward_eval(in.points, in.weight, in.gamma, in.beta, in.running_mean, in.running_var,
                         kHostPfnOptions, expected_eval);
  const cuda::PfnShape s = in.shape();
  GuardedArray<float> points(in.points), weight(in.weight), gamma(in.gamma), beta(in.beta),
      mean(in.running_mean), var(in.running_var), out(s.pillars * s.channels);
  GuardedArray<std::int32_t> max_slot(s.pillars * s.channels);
  cuda::pfn_forward_eval(points.data(), weight.data(), s, gamma.data(), beta.data(), mean.data(),
                         var.data(), kPfnEps, out.data(), max_slot.data(), nullptr);
  const std::vector<float> eval = out.download();
  EXPECT_TRUE(close(eval, expected_eval, 1e-5, 1e-5));
  for (std::int64_t c = 0; c < s.channels; ++c) {
    EXPECT_TRUE(std::isnan(eval[static_cast<std::size_t>(5 * s.channels + c)]));
    EXPECT_FALSE(std::isnan(eval[static_cast<std::size_t>(4 * s.channels + c)]));
  }
}

TEST(PfnKernels, SameBitsForEveryRunAndThreadCount) {
  const PfnInputs in = pfn_inputs(300, 20, 33, 1500);
  const PfnHostForward forward = host_pfn_train(in);
  const Tensor<float> d_out = normal_tensor({300, 33}, 1501);
  const PfnDeviceForward reference = device_pfn_train(in);
  const PfnGradients reference_gradients = device_pfn_backward(in, forward, d_out, true);
  const int threads = omp_get_max_threads();
  for (const int t : {1, 3}) {
    omp_set_num_threads(t);
    const PfnDeviceForward again = device_pfn_train(in);
    EXPECT_TRUE(same_bits(again.out, reference.out)) << t << " threads";
    EXPECT_TRUE(same_bits(again.save_inv_std, reference.save_inv_std));
    EXPECT_TRUE(same_bits(again.running_var, reference.running_var));
    const PfnGradients gradients = device_pfn_backward(in, forward, d_out, true);
    EXPECT_TRUE(same_bits(gradients.d_weight, reference_gradients.d_weight));
    EXPECT_TRUE(same_bits(gradients.d_gamma, reference_gradients.d_gamma));
    EXPECT_TRUE(same_bits(gradients.d_points, reference_gradients.d_points));
  }
  omp_set_num_threads(threads);
}

TEST(PfnKernels, LaunchersCheckTheirArguments) {
  cuda::DeviceBuffer<float> buffer(64);
  cuda::DeviceBuffer<std::int32_t> slots(4);
  cuda::DeviceBuffer<double> workspace(1024);
  float* p = buffer.data();
  const std::string one_row = kernel_test::error_message([&] {
    cuda::pfn_forward_train(p, p, {1, 1, 2}, p, p, kPfnEps, kPfnMomentum, p, p, p, slots.data(), p,
                            p, workspace.data(), nullptr);
  });
  EXPECT_NE(one_row.find("BatchNorm needs more than 1 row (P * N) when training"),
            std::string::npos)
      << one_row;
  const std::string no_slots = kernel_test::error_message([&] {
    cuda::pfn_forward_eval(p, p, {2, 0, 2}, p, p, p, p, kPfnEps, p, nullptr, nullptr);
  });
  EXPECT_NE(no_slots.find("with P >= 0, N >= 1"), std::string::npos) << no_slots;
  const std::string null_slots = kernel_test::error_message([&] {
    cuda::pfn_forward_train(p, p, {2, 2, 2}, p, p, kPfnEps, kPfnMomentum, p, p, p, nullptr, p, p,
                            workspace.data(), nullptr);
  });
  EXPECT_NE(null_slots.find("out and max_slot (4 values each) must be device memory"),
            std::string::npos)
      << null_slots;
}

// ---------------------------------------------------------------------------------------------
// Synchronised BatchNorm: this replica's sums combined with the other replicas' on the host (a
// ReplicaSum: the sums brought there) or on the device (a DeviceReplicaSum; NCCL's on a GPU is
// checked in tests/test_cuda_backend.cpp). The replicas here are R copies of this one, summed in
// replica order as MPI and NCCL sum R replicas (v + v + ... + v), by the host loop or by
// device copies and kernels/replica_sum.cu. The two paths must give the same bits (they run the
// same per-channel code); the statistics must be those of the batch of R copies (a wrong
// formula or a count left unsummed fails that); the device path must queue everything without
// waiting for the device (it runs inside a stream capture, which a synchronisation invalidates);
// the PFN, whose kernels/pfn.cu hands its ReplicaSum to the same finalize, takes the device path
// too.

namespace {

class CopiesOnHost final : public ReplicaSum {
 public:
  explicit CopiesOnHost(int copies) : copies_(copies) {}
  void sum(double* values, std::int64_t n) override {
    for (std::int64_t i = 0; i < n; ++i) {
      double total = values[i];
      for (int r = 1; r < copies_; ++r) total += values[i];
      values[i] = total;
    }
  }

 private:
  int copies_;
};

class CopiesOnDevice final : public cuda::DeviceReplicaSum {
 public:
  explicit CopiesOnDevice(int copies) : copies_(copies) {}
  void sum(double*, std::int64_t) override { throw Error("the device path summed host memory"); }
  // Exactly n doubles between guard words, so that a write past what the caller asked for shows.
  double* scratch(std::int64_t n) override {
    if (!scratch_ || scratch_->size() < n) scratch_ = std::make_unique<GuardedArray<double>>(n);
    return scratch_->data();
  }
  void sum(double* values, std::int64_t n, cudaStream_t stream) override {
    const auto bytes = static_cast<std::size_t>(n) * sizeof(double);
    if (gathered_.size() < static_cast<std::size_t>(copies_ * n)) {
      gathered_ = cuda::DeviceBuffer<double>(static_cast<std::size_t>(copies_ * n));
    }
    for (int r = 0; r < copies_; ++r) {
      PS_CUDA_CHECK(cudaMemcpyAsync(gathered_.data() + r * n, values, bytes,
                                    cudaMemcpyDeviceToDevice, stream));
    }
    cuda::sum_replica_chunks(gathered_.data(), copies_, n, values, stream);
    ++sums_;
  }
  int sums() const { return sums_; }
  ::testing::AssertionResult scratch_guards_intact() const {
    return scratch_ ? scratch_->guards_intact() : ::testing::AssertionFailure() << "no scratch";
  }

 private:
  int copies_;
  int sums_ = 0;
  std::unique_ptr<GuardedArray<double>> scratch_;
  cuda::DeviceBuffer<double> gathered_;
};

// R copies of x (B, C, H, W) along the batch: (R B, C, H, W).
Tensor<float> copies_along_batch(const Tensor<float>& x, std::int64_t copies) {
  Shape shape = x.shape();
  shape[0] *= copies;
  Tensor<float> all(shape);
  for (std::int64_t r = 0; r < copies; ++r)
    std::copy(x.begin(), x.end(), all.begin() + r * x.numel());
  return all;
}

// The first `numel` values of t as a tensor of `shape`.
Tensor<float> leading(const Tensor<float>& t, const Shape& shape) {
  Tensor<float> part(shape);
  std::copy(t.begin(), t.begin() + part.numel(), part.begin());
  return part;
}

const std::vector<BatchNormCase> kSynchronisedCases = {
    {{2, 4, 72, 64}, 0},  // float4, 4 parts per channel
    {{2, 5, 67, 65}, 1},  // scalar and misaligned, 4 parts
    {{3, 2, 1, 1}, 0},    // 3 values per channel: the unbiased variance's n / (n - 1) is large
    {{1, 33, 3, 4}, 0},   // C = 33: a second block of the one-thread-per-channel kernels
    {{0, 4, 5, 5}, 0},    // this replica holds no values
};

}  // namespace

TEST(SynchronisedBatchNormKernels, DeviceSumGivesTheHostPathsBits) {
  std::uint64_t seed = 1600;
  for (const BatchNormCase& c : kSynchronisedCases) {
    for (const bool relu : {false, true}) {
      for (const int copies : {1, 3}) {
        SCOPED_TRACE(case_name(c, relu) + ", " + std::to_string(copies) + " replicas");
        const BatchNormInputs in = batchnorm_inputs(c.shape, seed++);
        CopiesOnHost on_host(copies);
        CopiesOnDevice on_device(copies);
        const DeviceTrain host_path = device_train(in, relu, c.offset, &on_host);
        const DeviceTrain device_path = device_train(in, relu, c.offset, &on_device);
        EXPECT_EQ(on_device.sums(), 2) << "the sums and count, then the squares about the mean";
        EXPECT_TRUE(on_device.scratch_guards_intact());
        EXPECT_TRUE(same_bits(device_path.y, host_path.y)) << "y";
        EXPECT_TRUE(same_bits(device_path.save_mean, host_path.save_mean)) << "save_mean";
        EXPECT_TRUE(same_bits(device_path.save_inv_std, host_path.save_inv_std)) << "save_inv_std";
        EXPECT_TRUE(same_bits(device_path.running_mean, host_path.running_mean)) << "running_mean";
        EXPECT_TRUE(same_bits(device_path.running_var, host_path.running_var)) << "running_var";

        const HostTrain forward = host_train(in, relu);
        const Tensor<float> dy = normal_tensor(in.x.shape(), seed++);
        const BackwardResult host_backward =
            device_backward(in, forward, dy, relu, c.offset, &on_host);
        const BackwardResult device_backward_path =
            device_backward(in, forward, dy, relu, c.offset, &on_device);
        EXPECT_EQ(on_device.sums(), 3);
        EXPECT_TRUE(on_device.scratch_guards_intact());
        EXPECT_TRUE(same_bits(device_backward_path.dx, host_backward.dx)) << "dx";
        EXPECT_TRUE(same_bits(device_backward_path.dgamma, host_backward.dgamma)) << "dgamma";
        EXPECT_TRUE(same_bits(device_backward_path.dbeta, host_backward.dbeta)) << "dbeta";
      }
    }
  }
}

// R = 3 replicas holding the same values: their statistics are those of the batch of 3 copies,
// their input gradients those of that batch's first copy and their dgamma, dbeta a third of that
// batch's (each replica's share), as the host reference computes over the whole batch.
TEST(SynchronisedBatchNormKernels, StatisticsAreThoseOfAllReplicasValues) {
  constexpr int kCopies = 3;
  std::uint64_t seed = 1700;
  for (const BatchNormCase& c : kSynchronisedCases) {
    if (c.shape[0] == 0) continue;
    SCOPED_TRACE(case_name(c, true));
    const BatchNormInputs in = batchnorm_inputs(c.shape, seed++);
    BatchNormInputs all = in;
    all.x = copies_along_batch(in.x, kCopies);
    const HostTrain expected = host_train(all, true);
    for (const bool on_device : {false, true}) {
      SCOPED_TRACE(on_device ? "device sum" : "host sum");
      CopiesOnHost host_sum(kCopies);
      CopiesOnDevice device_sum(kCopies);
      ReplicaSum* replicas = on_device ? static_cast<ReplicaSum*>(&device_sum) : &host_sum;
      const DeviceTrain actual = device_train(in, true, c.offset, replicas);
      EXPECT_TRUE(close(actual.y, leading(expected.y, in.x.shape()), 1e-5, 1e-5)) << "y";
      EXPECT_TRUE(close(actual.save_mean, expected.saved.mean, 1e-6, 1e-6)) << "save_mean";
      EXPECT_TRUE(close(actual.save_inv_std, expected.saved.inv_std, 0.0, 1e-6)) << "save_inv_std";
      EXPECT_TRUE(close(actual.running_mean, expected.running_mean, 1e-7, 1e-6)) << "running_mean";
      EXPECT_TRUE(close(actual.running_var, expected.running_var, 1e-7, 1e-6)) << "running_var";

      const Tensor<float> dy = normal_tensor(in.x.shape(), seed);
      Tensor<float> dx_all, dgamma_all, dbeta_all;
      host::batchnorm_relu_backward(copies_along_batch(dy, kCopies), all.x, expected.y, in.gamma,
                                    expected.saved, dx_all, dgamma_all, dbeta_all);
      const HostTrain first_copy{leading(expected.y, in.x.shape()), expected.running_mean,
                                 expected.running_var, expected.saved};
      const BackwardResult gradients =
          device_backward(in, first_copy, dy, true, c.offset, replicas);
      EXPECT_TRUE(close(gradients.dx, leading(dx_all, in.x.shape()), 1e-5, 1e-5)) << "dx";
      for (float& g : dgamma_all) g /= kCopies;
      for (float& g : dbeta_all) g /= kCopies;
      EXPECT_TRUE(close(gradients.dgamma, dgamma_all, 1e-5, 1e-5)) << "dgamma";
      EXPECT_TRUE(close(gradients.dbeta, dbeta_all, 1e-5, 1e-5)) << "dbeta";
    }
    if (c.shape[0] * c.shape[2] * c.shape[3] == 3) {
      // What the comparisons above tell apart: one replica's own statistics (3 values, not 9).
      const DeviceTrain alone = device_train(in, true, c.offset);
      EXPECT_FALSE(close(alone.running_var, expected.running_var, 1e-7, 1e-6));
    }
    ++seed;
  }
}

// The device path inside a stream capture (global mode: any synchronisation or allocation fails
// and invalidates it), replayed: the same bits as outside. The host path inside a capture fails.
TEST(SynchronisedBatchNormKernels, DevicePathQueuesWithoutWaiting) {
  constexpr int kCopies = 3;
  const BatchNormInputs in = batchnorm_inputs({2, 4, 72, 64}, 1800);
  const Shape& shape = in.x.shape();
  const std::int64_t n = in.x.numel(), c = shape[1];
  const HostTrain forward = host_train(in, true);
  const Tensor<float> dy_values = normal_tensor(shape, 1801);
  GuardedArray<float> x(in.x), y(n), gamma(in.gamma), beta(in.beta), running_mean(c),
      running_var(c), save_mean(c), save_inv_std(c);
  GuardedArray<float> forward_y(forward.y), mean(forward.saved.mean),
      inv_std(forward.saved.inv_std), dy(dy_values), dx(n), dgamma(c), dbeta(c);
  GuardedArray<double> workspace(cuda::batchnorm_workspace_doubles(planar(shape)));
  cuda::Stream stream;
  CopiesOnDevice on_device(kCopies);
  const auto run = [&](ReplicaSum* replicas) {
    cuda::batchnorm_forward_train(x.data(), planar(shape), gamma.data(), beta.data(), kEps,
                                  kMomentum, running_mean.data(), running_var.data(), true,
                                  y.data(), save_mean.data(), save_inv_std.data(), workspace.data(),
                                  stream.get(), replicas);
    cuda::batchnorm_backward(dy.data(), x.data(), forward_y.data(), planar(shape), gamma.data(),
                             mean.data(), inv_std.data(), dx.data(), dgamma.data(), dbeta.data(),
                             workspace.data(), stream.get(), replicas);
  };
  const auto outputs = [&] {
    PS_CUDA_CHECK(cudaStreamSynchronize(stream.get()));
    return std::vector<std::vector<float>>{
        y.download(),         running_mean.download(), running_var.download(),
        save_mean.download(), save_inv_std.download(), dx.download(),
        dgamma.download(),    dbeta.download()};
  };
  const auto restart = [&] {
    running_mean.upload(std::vector<float>(in.running_mean.begin(), in.running_mean.end()));
    running_var.upload(std::vector<float>(in.running_var.begin(), in.running_var.end()));
    for (GuardedArray<float>* a : {&y, &save_mean, &save_inv_std, &dx, &dgamma, &dbeta}) {
      a->upload(std::vector<float>(static_cast<std::size_t>(a->size()), -1.0f));
    }
  };
  restart();
  run(&on_device);  // also sizes the sum's scratch: a capture may not allocate
  const std::vector<std::vector<float>> direct = outputs();

  restart();
  PS_CUDA_CHECK(cudaStreamBeginCapture(stream.get(), cudaStreamCaptureModeGlobal));
  run(&on_device);
  cudaGraph_t graph = nullptr;
  PS_CUDA_CHECK(cudaStreamEndCapture(stream.get(), &graph));
  EXPECT_EQ(on_device.sums(), 6);
  EXPECT_TRUE(same_bits(running_var.download(), in.running_var)) << "captured, not yet run";
  cudaGraphExec_t executable = nullptr;
  PS_CUDA_CHECK(cudaGraphInstantiate(&executable, graph, 0));
  PS_CUDA_CHECK(cudaGraphLaunch(executable, stream.get()));
  const std::vector<std::vector<float>> replayed = outputs();
  for (std::size_t i = 0; i < direct.size(); ++i) {
    EXPECT_TRUE(same_bits(replayed[i], direct[i])) << "output " << i;
  }
  EXPECT_TRUE(on_device.scratch_guards_intact());
  PS_CUDA_CHECK(cudaGraphExecDestroy(executable));
  PS_CUDA_CHECK(cudaGraphDestroy(graph));

  // The host path waits for the stream, which a capture refuses.
  CopiesOnHost on_host(kCopies);
  PS_CUDA_CHECK(cudaStreamBeginCapture(stream.get(), cudaStreamCaptureModeGlobal));
  const std::string waited = kernel_test::error_message([&] { run(&on_host); });
  EXPECT_FALSE(waited.empty()) << "the host path ran inside a capture";
  cudaGraph_t invalidated = nullptr;
  EXPECT_EQ(cudaStreamEndCapture(stream.get(), &invalidated), cudaErrorStreamCaptureInvalidated);
  static_cast<void>(cudaGetLastError());
}

TEST(SynchronisedPfnKernels, DeviceSumGivesTheHostPathsBits) {
  std::uint64_t seed = 1900;
  for (const PfnCase& c : {PfnCase{37, 20, 64}, PfnCase{300, 20, 33}, PfnCase{0, 20, 8}}) {
    for (const int copies : {1, 3}) {
      SCOPED_TRACE(pfn_case_name(c) + ", " + std::to_string(copies) + " replicas");
      const PfnInputs in = pfn_inputs(c.pillars, c.slots, c.channels, seed++);
      CopiesOnHost on_host(copies);
      CopiesOnDevice on_device(copies);
      const PfnDeviceForward host_path = device_pfn_train(in, &on_host);
      const PfnDeviceForward device_path = device_pfn_train(in, &on_device);
      EXPECT_EQ(on_device.sums(), 2);
      EXPECT_TRUE(same_bits(device_path.out, host_path.out)) << "out";
      EXPECT_TRUE(same_bits(device_path.max_slot, host_path.max_slot)) << "max_slot";
      EXPECT_TRUE(same_bits(device_path.save_mean, host_path.save_mean)) << "save_mean";
      EXPECT_TRUE(same_bits(device_path.save_inv_std, host_path.save_inv_std)) << "save_inv_std";
      EXPECT_TRUE(same_bits(device_path.running_var, host_path.running_var)) << "running_var";

      const PfnHostForward forward = host_pfn_train(in);
      const Tensor<float> d_out = normal_tensor({c.pillars, c.channels}, seed++);
      const PfnGradients host_gradients = device_pfn_backward(in, forward, d_out, true, &on_host);
      const PfnGradients device_gradients =
          device_pfn_backward(in, forward, d_out, true, &on_device);
      EXPECT_EQ(on_device.sums(), 3);
      EXPECT_TRUE(on_device.scratch_guards_intact());
      EXPECT_TRUE(same_bits(device_gradients.d_weight, host_gradients.d_weight)) << "d_weight";
      EXPECT_TRUE(same_bits(device_gradients.d_gamma, host_gradients.d_gamma)) << "d_gamma";
      EXPECT_TRUE(same_bits(device_gradients.d_beta, host_gradients.d_beta)) << "d_beta";
      EXPECT_TRUE(same_bits(device_gradients.d_points, host_gradients.d_points)) << "d_points";
    }
  }
}
