// kernels/reduce.cu (sum_of_squares) and kernels/replica_sum.cu (the replica-order gradient sum),
// run on
// the CUDA emulation and compared with plain host loops: sizes around the warp, block and float4
// boundaries up to 2^20 + 3, pointers at every 4-byte misalignment (float4 path with scalar head
// and tail; mixed misalignments take the scalar path), NaN, Inf and -0 inputs, in-place use, guard
// words before and after every output, determinism across runs, thread counts and alignments, and
// the launchers' argument checks.
#include <gtest/gtest.h>
#include <omp.h>

#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "core/rng.hpp"
#include "kernels/common.cuh"
#include "kernels/device_buffer.hpp"
#include "kernels/reduce.cuh"
#include "kernels/replica_sum.cuh"

using namespace pillarseg;
using cuda::DeviceBuffer;

namespace {

const std::vector<std::int64_t> kSizes = {0, 1, 31, 32, 33, 1000, (1 << 20) + 3};
constexpr std::int64_t kGuardFloats = 16;
constexpr std::uint32_t kGuardBits = 0x7FC0DEADu;  // a NaN payload no kernel produces

// n floats of device memory at `offset` floats past a 64-byte boundary (so offsets 0..3 give
// every 4-byte misalignment modulo 16), with kGuardFloats guard words before and after.
class GuardedDeviceArray {
 public:
  GuardedDeviceArray(std::int64_t n, std::int64_t offset)
      : n_(n), offset_(offset), storage_(static_cast<size_t>(2 * kGuardFloats + offset + n)) {
    const std::vector<float> guards(storage_.size(), std::bit_cast<float>(kGuardBits));
    storage_.copy_from_host(guards);
  }
  float* data() { return storage_.data() + kGuardFloats + offset_; }
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

std::string error_message(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

struct Offsets {
  std::int64_t a, b, c;
};
// Same misalignment for every pointer (float4 path with heads of 0..3 elements), then mixed.
const std::vector<Offsets> kOffsets = {{0, 0, 0}, {1, 1, 1}, {2, 2, 2},
                                       {3, 3, 3}, {0, 1, 2}, {3, 0, 1}};

}  // namespace

namespace {

// sum_of_squares of `x` placed at `offset` floats past a 64-byte boundary; checks the guards
// around the scratch and the result.
double device_sum_of_squares(const std::vector<float>& x, std::int64_t offset) {
  const auto n = static_cast<std::int64_t>(x.size());
  GuardedDeviceArray device_x(n, offset);
  device_x.upload(x);
  // Scratch and result as doubles between guard doubles.
  const std::int64_t guard = 4;
  const double guard_value = std::bit_cast<double>(0x7FF8DEADDEADDEADull);
  const std::int64_t scratch_size = guard + cuda::kSumOfSquaresPartials + guard + 1 + guard;
  auto scratch = DeviceBuffer<double>::from_host(
      std::vector<double>(static_cast<size_t>(scratch_size), guard_value));
  double* partials = scratch.data() + guard;
  double* result = partials + cuda::kSumOfSquaresPartials + guard;
  cuda::sum_of_squares(device_x.data(), n, partials, result, nullptr);
  const std::vector<double> host = scratch.to_host();
  for (std::int64_t i = 0; i < scratch_size; ++i) {
    const bool is_partial = i >= guard && i < guard + cuda::kSumOfSquaresPartials;
    const bool is_result = i == guard + cuda::kSumOfSquaresPartials + guard;
    if (is_partial || is_result) continue;
    EXPECT_EQ(std::bit_cast<std::uint64_t>(host[static_cast<size_t>(i)]),
              std::bit_cast<std::uint64_t>(guard_value))
        << "guard word " << i << " overwritten";
  }
  return host[static_cast<size_t>(guard + cuda::kSumOfSquaresPartials + guard)];
}

std::vector<float> finite_values(std::int64_t n, std::uint64_t seed) {
  Rng rng(seed);
  std::vector<float> values(static_cast<size_t>(n));
  for (float& v : values) v = static_cast<float>(rng.normal() * 3.0);
  return values;
}

}  // namespace

TEST(ReduceKernels, SumOfSquaresMatchesTheHostLoop) {
  for (const std::int64_t n : kSizes) {
    const std::vector<float> x = finite_values(n, 10 + static_cast<std::uint64_t>(n));
    long double expected = 0.0L;
    for (const float v : x) expected += static_cast<long double>(v) * v;
    for (const std::int64_t offset : {0, 1, 2, 3}) {
      const double actual = device_sum_of_squares(x, offset);
      EXPECT_NEAR(actual, static_cast<double>(expected), 1e-13 * static_cast<double>(expected))
          << "n " << n << ", offset " << offset;
    }
  }
}

TEST(ReduceKernels, HandComputedSums) {
  EXPECT_EQ(device_sum_of_squares({}, 0), 0.0);
  EXPECT_EQ(device_sum_of_squares({-3.0f}, 0), 9.0);
  EXPECT_EQ(device_sum_of_squares({3.0f, 4.0f}, 1), 25.0);
  // 1e20^2 overflows float but not the double accumulator.
  EXPECT_EQ(device_sum_of_squares({1e20f, -1e20f}, 2),
            2.0 * static_cast<double>(1e20f) * static_cast<double>(1e20f));
  // 2^20 + 3 ones: every partial and the final sum are exact integers.
  EXPECT_EQ(device_sum_of_squares(std::vector<float>((1 << 20) + 3, 1.0f), 3),
            static_cast<double>((1 << 20) + 3));
}

TEST(ReduceKernels, NanAndInfPropagate) {
  std::vector<float> x = finite_values(5000, 7);
  x[4321] = std::numeric_limits<float>::infinity();
  EXPECT_EQ(device_sum_of_squares(x, 0), std::numeric_limits<double>::infinity());
  x[17] = std::numeric_limits<float>::quiet_NaN();
  EXPECT_TRUE(std::isnan(device_sum_of_squares(x, 1)));
}

TEST(ReduceKernels, SameBitsForEveryRunThreadCountAndAlignment) {
  const std::vector<float> x = finite_values((1 << 18) + 77, 99);
  const double reference = device_sum_of_squares(x, 0);
  const int threads = omp_get_max_threads();
  for (const int t : {1, 2, 3}) {
    omp_set_num_threads(t);
    for (const std::int64_t offset : {0, 1, 3}) {
      EXPECT_EQ(std::bit_cast<std::uint64_t>(device_sum_of_squares(x, offset)),
                std::bit_cast<std::uint64_t>(reference))
          << t << " threads, offset " << offset;
    }
  }
  omp_set_num_threads(threads);
}

TEST(ReduceKernels, LauncherChecksItsArguments) {
  DeviceBuffer<float> x(4);
  DeviceBuffer<double> scratch(cuda::kSumOfSquaresPartials + 1);
  const std::string negative = error_message([&] {
    cuda::sum_of_squares(x.data(), -5, scratch.data(), scratch.data() + cuda::kSumOfSquaresPartials,
                         nullptr);
  });
  EXPECT_NE(negative.find("sum_of_squares: n = -5"), std::string::npos) << negative;
  const std::string null_x = error_message([&] {
    cuda::sum_of_squares(nullptr, 4, scratch.data(), scratch.data() + cuda::kSumOfSquaresPartials,
                         nullptr);
  });
  EXPECT_NE(null_x.find("sum_of_squares: x is null with n = 4 elements"), std::string::npos)
      << null_x;
  const std::string null_result =
      error_message([&] { cuda::sum_of_squares(x.data(), 4, scratch.data(), nullptr, nullptr); });
  EXPECT_NE(null_result.find("must be device memory"), std::string::npos) << null_result;
}

// The replicas' chunks added in replica order: the same bits as the host loop in that order,
// which for these values differ from another order's (1 + 3e-8 + 3e-8 != 1 + (3e-8 + 3e-8) in
// float, 1 + 1e-16 + 1e-16 != 1 + (1e-16 + 1e-16) in double); floats are the gradients', doubles
// the BatchNorm statistics'.
template <class T>
void expect_sums_in_replica_order(const T (&scale)[4]) {
  for (const std::int64_t n : {std::int64_t{1}, std::int64_t{33}, std::int64_t{1000}, std::int64_t{(1 << 20) + 3}}) {
    for (const int replicas : {1, 3, 4}) {
      SCOPED_TRACE("n " + std::to_string(n) + ", replicas " + std::to_string(replicas));
      std::vector<T> chunks(static_cast<size_t>(n * replicas));
      for (int r = 0; r < replicas; ++r) {
        for (std::int64_t i = 0; i < n; ++i) {
          chunks[static_cast<size_t>(r * n + i)] =
              scale[r] * (T(1) + static_cast<T>(i % 5) * T(0.25));
        }
      }
      auto device_chunks = DeviceBuffer<T>::from_host(chunks);
      auto out = DeviceBuffer<T>::from_host(std::vector<T>(static_cast<size_t>(n) + 1, T(-7)));
      cuda::sum_replica_chunks(device_chunks.data(), replicas, n, out.data(), nullptr);
      const std::vector<T> host = out.to_host();
      for (std::int64_t i = 0; i < n; ++i) {
        T expected = chunks[static_cast<size_t>(i)];
        for (int r = 1; r < replicas; ++r) expected += chunks[static_cast<size_t>(r * n + i)];
        ASSERT_EQ(std::memcmp(&host[static_cast<size_t>(i)], &expected, sizeof(T)), 0)
            << "i " << i << ": " << host[static_cast<size_t>(i)] << " != expected " << expected;
      }
      EXPECT_EQ(host[static_cast<size_t>(n)], T(-7)) << "guard after the output";
    }
  }
  EXPECT_NE(T(1) + scale[1] + scale[2], T(1) + (scale[1] + scale[2]))
      << "the values above must tell the order apart";
  const std::string bad = error_message(
      [] { cuda::sum_replica_chunks(static_cast<const T*>(nullptr), 0, 4, nullptr, nullptr); });
  EXPECT_NE(bad.find("expected replicas >= 1"), std::string::npos) << bad;
}

TEST(ReplicaSumKernels, AddsFloatsInReplicaOrder) {
  const float scale[] = {1.0f, 3e-8f, 3e-8f, -0.5f};
  expect_sums_in_replica_order(scale);
}

TEST(ReplicaSumKernels, AddsDoublesInReplicaOrder) {
  const double scale[] = {1.0, 1e-16, 1e-16, -0.5};
  expect_sums_in_replica_order(scale);
}
