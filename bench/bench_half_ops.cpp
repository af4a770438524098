// The CPU's 16-bit data movement (engine/cpu/half_ops.hpp) at the full-size network's shapes
// (the default grid, 500 x 1000 cells, b = 64, depth 4, bilinear): the 2x2 max-pools of the four
// Down blocks, the x2 upsamplings of the four Up blocks, and the scatter of 32,768 pillars (the
// benched scan's count, at random distinct cells in cell order) into the (1, 64, 500, 1000)
// canvas; BF16, on the scalar loops and on AVX-512 (skipped with the reason where it cannot run),
// all threads (set with --threads=T, default 2). Reports ms and the least bytes each call moves
// (inputs read once, outputs written once) as GB/s.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <numeric>
#include <random>
#include <string>
#include <vector>

#include "core/ops.hpp"
#include "core/parallel.hpp"
#include "engine/cpu/cpu_features.hpp"
#include "engine/cpu/half_ops.hpp"
#include "weights_io/half.hpp"

using namespace pillarseg;
using cpu::HalfOpsKernels;

namespace {

std::vector<std::uint16_t> random_bf16(std::int64_t n, std::uint32_t seed) {
  std::mt19937 gen(seed);
  std::normal_distribution<float> d(0.0f, 1.0f);
  std::vector<std::uint16_t> v(static_cast<size_t>(n));
  for (std::uint16_t& x : v) x = weights::float_to_bf16_bits(d(gen));
  return v;
}

// False (with the benchmark skipped, saying why) where `kernels` cannot run here.
bool runs(benchmark::State& state, HalfOpsKernels kernels) {
  std::string why;
  if (kernels == HalfOpsKernels::Avx512 && !cpu::avx512_half_ops_available(&why)) {
    state.SkipWithError(("AVX-512 16-bit data movement unavailable: " + why).c_str());
    return false;
  }
  return true;
}

void report(benchmark::State& state, double bytes) {
  state.SetBytesProcessed(static_cast<std::int64_t>(bytes) * state.iterations());
}

void BM_MaxPool(benchmark::State& state, Shape x_shape, HalfOpsKernels kernels) {
  if (!runs(state, kernels)) return;
  const Shape y_shape = op::maxpool2d(x_shape);
  std::vector<std::uint16_t> x = random_bf16(shape_numel(x_shape), 1), y(static_cast<size_t>(shape_numel(y_shape)));
  HRef yr{y.data(), y_shape};
  for (auto _ : state) {
    cpu::maxpool2d_half(HRef{x.data(), x_shape}, Precision::BF16, yr, kernels);
    benchmark::DoNotOptimize(y.data());
  }
  report(state, 2.0 * static_cast<double>(x.size() + y.size()));
}

void BM_Upsample(benchmark::State& state, Shape x_shape, HalfOpsKernels kernels) {
  if (!runs(state, kernels)) return;
  const Shape y_shape = op::upsample_bilinear(x_shape);
  std::vector<std::uint16_t> x = random_bf16(shape_numel(x_shape), 2), y(static_cast<size_t>(shape_numel(y_shape)));
  HRef yr{y.data(), y_shape};
  for (auto _ : state) {
    cpu::upsample_bilinear_half(HRef{x.data(), x_shape}, Precision::BF16, yr, kernels);
    benchmark::DoNotOptimize(y.data());
  }
  report(state, 2.0 * static_cast<double>(x.size() + y.size()));
}

void BM_Scatter(benchmark::State& state, HalfOpsKernels kernels) {
  if (!runs(state, kernels)) return;
  const std::int64_t pillars = 32768, channels = 64, height = 500, width = 1000;
  std::vector<std::int32_t> cell_ids(static_cast<size_t>(height * width));
  std::iota(cell_ids.begin(), cell_ids.end(), 0);
  std::mt19937 gen(3);
  std::shuffle(cell_ids.begin(), cell_ids.end(), gen);
  cell_ids.resize(static_cast<size_t>(pillars));
  std::sort(cell_ids.begin(), cell_ids.end());
  std::vector<std::int32_t> cells(static_cast<size_t>(3 * pillars));
  for (std::int64_t r = 0; r < pillars; ++r) {
    cells[static_cast<size_t>(3 * r + 1)] = static_cast<std::int32_t>(cell_ids[static_cast<size_t>(r)] / width);
    cells[static_cast<size_t>(3 * r + 2)] = static_cast<std::int32_t>(cell_ids[static_cast<size_t>(r)] % width);
  }
  std::normal_distribution<float> d(0.0f, 1.0f);
  std::vector<float> features(static_cast<size_t>(pillars * channels));
  for (float& f : features) f = d(gen);
  std::vector<std::uint16_t> canvas(static_cast<size_t>(channels * height * width));
  HRef cr{canvas.data(), {1, channels, height, width}};
  for (auto _ : state) {
    cpu::scatter_half(Ref{features.data(), {pillars, channels}}, IRef{cells.data(), {pillars, 3}}, 0,
                      Precision::BF16, cr, kernels);
    benchmark::DoNotOptimize(canvas.data());
  }
  report(state, 4.0 * static_cast<double>(features.size()) + 12.0 * pillars + 2.0 * static_cast<double>(canvas.size()));
}

const char* kernels_name(HalfOpsKernels kernels) {
  return kernels == HalfOpsKernels::Scalar ? "scalar" : "avx512";
}

void register_all() {
  const std::vector<Shape> pools = {{1, 64, 500, 1000}, {1, 128, 250, 500}, {1, 256, 125, 250}, {1, 512, 62, 125}};
  const std::vector<Shape> ups = {{1, 512, 31, 62}, {1, 256, 62, 125}, {1, 128, 125, 250}, {1, 64, 250, 500}};
  const auto in_ms = [](benchmark::internal::Benchmark* b) { b->Unit(benchmark::kMillisecond)->UseRealTime(); };
  for (HalfOpsKernels kernels : {HalfOpsKernels::Scalar, HalfOpsKernels::Avx512}) {
    const std::string k = kernels_name(kernels);
    for (const Shape& s : pools)
      in_ms(benchmark::RegisterBenchmark(("maxpool/" + k + "/" + shape_str(s)).c_str(), BM_MaxPool, s, kernels));
    for (const Shape& s : ups)
      in_ms(benchmark::RegisterBenchmark(("upsample/" + k + "/" + shape_str(s)).c_str(), BM_Upsample, s, kernels));
    in_ms(benchmark::RegisterBenchmark(("scatter/" + k).c_str(), BM_Scatter, kernels));
  }
}

}  // namespace

int main(int argc, char** argv) {
  int threads = 2;
  std::vector<char*> rest;
  for (int i = 0; i < argc; ++i) {
    if (std::strncmp(argv[i], "--threads=", 10) == 0) {
      threads = std::atoi(argv[i] + 10);
    } else {
      rest.push_back(argv[i]);
    }
  }
  set_num_threads(threads);
  int rest_count = static_cast<int>(rest.size());
  benchmark::Initialize(&rest_count, rest.data());
  register_all();
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
