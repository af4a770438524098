// Helpers shared by the tests: paths to the shared data, temporary directories, tolerant
// tensor comparison that reports the worst element.
#pragma once

#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <functional>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "core/rng.hpp"
#include "core/tensor.hpp"

namespace pillarseg::test {

// ../shared/data (the real SemanticKITTI scan lives in semantickitti/sequences/99).
std::filesystem::path shared_data_dir();
// A fresh, empty directory under the build tree, named after the running test.
std::filesystem::path temp_dir();

// Compares element-wise with |a - b| <= atol + rtol * |b|; NaN and Inf must match. On failure
// the message names the worst element, its index, and both values.
::testing::AssertionResult all_close(const float* actual, const float* expected, int64_t n, double atol,
                                     double rtol);
::testing::AssertionResult all_close(const double* actual, const double* expected, int64_t n, double atol,
                                     double rtol);
template <class T>
::testing::AssertionResult all_close(const Tensor<T>& actual, const Tensor<T>& expected, double atol,
                                     double rtol) {
  if (actual.shape() != expected.shape())
    return ::testing::AssertionFailure()
           << "shape " << shape_str(actual.shape()) << " != expected " << shape_str(expected.shape());
  return all_close(actual.data(), expected.data(), actual.numel(), atol, rtol);
}

// An output as the model's executor passes it: a view of arena memory holding NaN, already of
// its shape (a view keeps its memory when resized, so nothing zeroes it): an op that leaves any
// element unwritten, or adds into what was there, shows NaN.
template <class T>
struct StaleView {
  explicit StaleView(const Shape& shape)
      : memory(static_cast<size_t>(shape_numel(shape)), std::numeric_limits<T>::quiet_NaN()),
        tensor(Tensor<T>::view(memory.data(), shape)) {}
  StaleView(const StaleView&) = delete;  // the view would still point at the original's memory
  StaleView& operator=(const StaleView&) = delete;
  std::vector<T> memory;
  Tensor<T> tensor;
};

// Elements drawn uniformly from [lo, hi).
template <class T = double>
Tensor<T> random_tensor(const Shape& shape, Rng& rng, double lo = -1, double hi = 1) {
  Tensor<T> t(shape);
  for (int64_t i = 0; i < t.numel(); ++i) t[i] = static_cast<T>(rng.uniform(lo, hi));
  return t;
}

// The message of the pillarseg::Error that f throws ("" if none).
template <class F>
std::string error_of(F&& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

// Sets an environment variable (value null: unsets it) for the scope of the object and restores
// it afterwards.
class ScopedEnv {
 public:
  ScopedEnv(const char* name, const char* value) : name_(name) {
    if (const char* old = std::getenv(name)) old_ = old;
    if (value)
      ::setenv(name, value, 1);
    else
      ::unsetenv(name);
  }
  ~ScopedEnv() {
    if (old_)
      ::setenv(name_, old_->c_str(), 1);
    else
      ::unsetenv(name_);
  }
  ScopedEnv(const ScopedEnv&) = delete;
  ScopedEnv& operator=(const ScopedEnv&) = delete;

 private:
  const char* name_;
  std::optional<std::string> old_;
};

// Sum of a[i] * b[i] (a scalar functional for gradient checks).
double dot(const TensorD& a, const TensorD& b);

// Central differences (f(v + h) - f(v - h)) / 2h of the scalar f along every element v of
// value, which f reads.
TensorD numeric_gradient(TensorD& value, const std::function<double()>& f, double h = 1e-6);

}  // namespace pillarseg::test
