// Helpers of the emulated kernel tests (tests/test_kernels_*.cpp): device arrays between guard
// words (to catch writes outside an output), random inputs, bitwise comparison (for determinism
// and exact ops) and the normalised mean squared error (for large reductions).
#pragma once

#include <gtest/gtest.h>

#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <functional>
#include <string>
#include <utility>
#include <vector>

#include "core/error.hpp"
#include "core/rng.hpp"
#include "core/tensor.hpp"
#include "kernels/common.cuh"
#include "kernels/device_buffer.hpp"

namespace pillarseg::kernel_test {

// n values of T in device memory `offset` elements past a 256-byte boundary (offsets that are
// not multiples of 4 floats take the kernels' unaligned paths), with kGuardElements guard
// elements of the byte 0xA7 before and after.
template <class T>
class GuardedArray {
 public:
  static constexpr std::int64_t kGuardElements = 64;
  static constexpr unsigned char kGuardByte = 0xA7;

  explicit GuardedArray(std::int64_t n, std::int64_t offset = 0)
      : n_(n),
        start_(kGuardElements + offset),
        storage_(static_cast<std::size_t>(2 * kGuardElements + offset + n)) {
    PS_CUDA_CHECK(cudaMemset(storage_.data(), kGuardByte, storage_.bytes()));
  }
  // The same, holding `values`.
  explicit GuardedArray(const std::vector<T>& values, std::int64_t offset = 0)
      : GuardedArray(static_cast<std::int64_t>(values.size()), offset) {
    upload(values);
  }
  explicit GuardedArray(const Tensor<T>& values, std::int64_t offset = 0)
      : GuardedArray(std::vector<T>(values.begin(), values.end()), offset) {}

  T* data() { return storage_.data() + start_; }
  const T* data() const { return storage_.data() + start_; }
  std::int64_t size() const { return n_; }

  void upload(const std::vector<T>& values) {
    PS_CHECK(static_cast<std::int64_t>(values.size()) == n_, "upload of {} values into {}",
             values.size(), n_);
    if (n_ > 0) {
      PS_CUDA_CHECK(
          cudaMemcpy(data(), values.data(), values.size() * sizeof(T), cudaMemcpyHostToDevice));
    }
  }
  std::vector<T> download() const {
    const std::vector<T> all = storage_.to_host();
    return std::vector<T>(all.begin() + start_, all.begin() + start_ + n_);
  }
  Tensor<T> download(const Shape& shape) const {
    const std::vector<T> values = download();
    Tensor<T> t(shape);
    PS_CHECK(t.numel() == n_, "download of {} values as {}", n_, shape_str(shape));
    std::copy(values.begin(), values.end(), t.begin());
    return t;
  }

  // Reads back the guards alone (not the elements between them: a workspace's contents may
  // legitimately differ from run to run, and the emulation's schedule digests compare every
  // copy).
  ::testing::AssertionResult guards_intact() const {
    const auto total = static_cast<std::int64_t>(storage_.size());
    for (const auto& [first, last] :
         {std::pair{std::int64_t{0}, start_}, std::pair{start_ + n_, total}}) {
      if (last <= first) continue;
      std::vector<unsigned char> bytes(static_cast<std::size_t>(last - first) * sizeof(T));
      PS_CUDA_CHECK(
          cudaMemcpy(bytes.data(), storage_.data() + first, bytes.size(), cudaMemcpyDeviceToHost));
      for (std::size_t b = 0; b < bytes.size(); ++b) {
        if (bytes[b] != kGuardByte) {
          const std::int64_t element = first + static_cast<std::int64_t>(b / sizeof(T));
          return ::testing::AssertionFailure() << "guard element " << element - start_
                                               << " (outside [0, " << n_ << ")) was overwritten";
        }
      }
    }
    return ::testing::AssertionSuccess();
  }

 private:
  std::int64_t n_;
  std::int64_t start_;
  cuda::DeviceBuffer<T> storage_;
};

// n values mean + spread * N(0, 1) (seeded).
inline std::vector<float> normal_values(std::int64_t n, std::uint64_t seed, double spread = 1.0,
                                        double mean = 0.0) {
  Rng rng(seed);
  std::vector<float> values(static_cast<std::size_t>(n));
  for (float& v : values) v = static_cast<float>(mean + spread * rng.normal());
  return values;
}

inline Tensor<float> normal_tensor(const Shape& shape, std::uint64_t seed, double spread = 1.0,
                                   double mean = 0.0) {
  Tensor<float> t(shape);
  const std::vector<float> values = normal_values(t.numel(), seed, spread, mean);
  std::copy(values.begin(), values.end(), t.begin());
  return t;
}

inline std::vector<float> to_vector(const Tensor<float>& t) {
  return std::vector<float>(t.begin(), t.end());
}

// Bitwise equality (NaN payloads included), naming the first differing element.
template <class T>
::testing::AssertionResult same_bits(const std::vector<T>& actual, const std::vector<T>& expected) {
  if (actual.size() != expected.size()) {
    return ::testing::AssertionFailure() << "size " << actual.size() << " != " << expected.size();
  }
  for (std::size_t i = 0; i < actual.size(); ++i) {
    if (std::memcmp(&actual[i], &expected[i], sizeof(T)) != 0) {
      return ::testing::AssertionFailure()
             << "element " << i << ": " << +actual[i] << " != expected " << +expected[i];
    }
  }
  return ::testing::AssertionSuccess();
}

template <class T>
::testing::AssertionResult same_bits(const std::vector<T>& actual, const Tensor<T>& expected) {
  return same_bits(actual, std::vector<T>(expected.begin(), expected.end()));
}

// sum (a - e)^2 / sum e^2 (0 for two zero arrays): the error of a large reduction relative to
// its size, independent of the order of the sums.
inline double normalized_mse(const std::vector<float>& actual, const std::vector<float>& expected) {
  double error = 0.0;
  double norm = 0.0;
  for (std::size_t i = 0; i < expected.size(); ++i) {
    const double d = static_cast<double>(actual[i]) - expected[i];
    error += d * d;
    norm += static_cast<double>(expected[i]) * expected[i];
  }
  return norm > 0.0 ? error / norm : error;
}

// The message of the pillarseg::Error that fn throws, or "" if it throws none.
inline std::string error_message(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

}  // namespace pillarseg::kernel_test
