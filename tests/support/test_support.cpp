#include "tests/support/test_support.hpp"
#include "tests/support/tiny_model.hpp"

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

ModelConfig tiny_config(OccupancyInput occupancy, bool transposed, bool grid_map) {
  ModelConfig c;
  c.grid.x_min = 0, c.grid.x_max = 2.4, c.grid.y_min = 0, c.grid.y_max = 1.6;  // 24 x 16 cells
  c.grid.z_min = -1, c.grid.z_max = 1, c.grid.voxel_z = 0.5;                   // 4 layers
  c.max_points_per_pillar = 3;
  c.pillar_channels = 4;
  c.occupancy = occupancy;
  c.occupancy_channels = 3;
  c.grid_map_input = grid_map;
  c.base_width = 4;
  c.depth = 2;
  c.transposed = transposed;
  return c;
}

TinyData tiny_data(const ModelConfig& c, int B, uint64_t seed, double density) {
  Rng rng(seed);
  TinyData d;
  const int H = c.grid.height(), W = c.grid.width(), N = c.max_points_per_pillar;
  std::vector<std::array<int32_t, 3>> cells;
  for (int b = 0; b < B; ++b)
    for (int y = 0; y < H; ++y)
      for (int x = 0; x < W; ++x)
        if (rng.bernoulli(density)) cells.push_back({b, y, x});
  const int64_t P = static_cast<int64_t>(cells.size());
  d.batch.batch = B;
  d.batch.pillar_points = Tensor<float>({P, N, 10});
  d.batch.pillar_cells = Tensor<int32_t>({P, 3});
  for (int64_t p = 0; p < P; ++p) {
    for (int k = 0; k < 3; ++k)
      d.batch.pillar_cells(p, k) = cells[static_cast<size_t>(p)][static_cast<size_t>(k)];
    const int n = 1 + static_cast<int>(rng.uniform_int(N));
    for (int s = 0; s < n; ++s)
      for (int f = 0; f < 10; ++f)
        d.batch.pillar_points(p, s, f) = static_cast<float>(rng.normal());
  }
  if (c.occupancy != OccupancyInput::None) {
    d.batch.occupancy = Tensor<float>({B, c.occupancy_input_channels(), H, W});
    for (float& v : d.batch.occupancy) v = static_cast<float>(rng.uniform());
  }
  if (c.grid_map_input) {
    d.batch.grid_map = Tensor<float>({B, 6, H, W});
    for (float& v : d.batch.grid_map) v = static_cast<float>(rng.normal());
  }
  d.labels = Tensor<uint8_t>({B, H, W});
  for (auto& l : d.labels) l = static_cast<uint8_t>(rng.uniform_int(13));
  return d;
}

}  // namespace pillarseg::test
