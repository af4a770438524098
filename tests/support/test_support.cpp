#include "tests/support/test_support.hpp"

#include <cmath>
#include <sstream>

namespace pillarseg::test {

namespace fs = std::filesystem;

fs::path shared_data_dir() { return fs::path(PILLARSEG_SHARED_DATA); }

fs::path temp_dir() {
  const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
  std::string name = info ? std::string(info->test_suite_name()) + "." + info->name() : "no_test";
  for (char& c : name)
    if (c == '/') c = '_';
  const fs::path dir = fs::path(PILLARSEG_BINARY_DIR) / "test_tmp" / name;
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

namespace {
template <class T>
::testing::AssertionResult all_close_impl(const T* actual, const T* expected, int64_t n, double atol, double rtol) {
  int64_t worst = -1, failures = 0;
  double worst_excess = 0;
  for (int64_t i = 0; i < n; ++i) {
    const double a = actual[i], e = expected[i];
    bool ok;
    double excess = 0;
    if (std::isnan(e) || std::isnan(a)) {
      ok = std::isnan(e) && std::isnan(a);
      excess = ok ? 0 : INFINITY;
    } else if (std::isinf(e) || std::isinf(a)) {
      ok = a == e;
      excess = ok ? 0 : INFINITY;
    } else {
      const double tol = atol + rtol * std::abs(e);
      excess = std::abs(a - e) - tol;
      ok = excess <= 0;
    }
    if (!ok) {
      ++failures;
      if (worst < 0 || excess > worst_excess) worst = i, worst_excess = excess;
    }
  }
  if (failures == 0) return ::testing::AssertionSuccess();
  std::ostringstream s;
  s.precision(9);
  s << failures << " of " << n << " elements differ (atol " << atol << ", rtol " << rtol << "); worst at index "
    << worst << ": actual " << actual[worst] << ", expected " << expected[worst];
  return ::testing::AssertionFailure() << s.str();
}
}  // namespace

double dot(const TensorD& a, const TensorD& b) {
  double s = 0;
  for (int64_t i = 0; i < a.numel(); ++i) s += a[i] * b[i];
  return s;
}

TensorD numeric_gradient(TensorD& value, const std::function<double()>& f, double h) {
  TensorD grad(value.shape());
  for (int64_t i = 0; i < value.numel(); ++i) {
    const double saved = value[i];
    value[i] = saved + h;
    const double plus = f();
    value[i] = saved - h;
    const double minus = f();
    value[i] = saved;
    grad[i] = (plus - minus) / (2 * h);
  }
  return grad;
}

::testing::AssertionResult all_close(const float* a, const float* e, int64_t n, double atol, double rtol) {
  return all_close_impl(a, e, n, atol, rtol);
}
::testing::AssertionResult all_close(const double* a, const double* e, int64_t n, double atol, double rtol) {
  return all_close_impl(a, e, n, atol, rtol);
}

}  // namespace pillarseg::test
