// CPU reference conv2d (host/conv2d: im2col + Eigen GEMM) at U-Net layer shapes: forward and
// backward (dx + dw + db) times in ms and GFLOP/s (2 B O I k k Ho Wo flops per pass; backward
// counts two passes, dx and dw). The peer is one Eigen GEMM of the forward's size,
// (O x I k k) * (I k k x B Ho Wo), on Eigen's own threads: the conv's GFLOP/s over the GEMM's is
// what im2col and tiling cost.
#include <benchmark/benchmark.h>

#include <cstdint>
#include <string>

#include "core/eigen.hpp"
#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "host/conv2d.hpp"

using namespace pillarseg;

namespace {

struct Layer {
  const char* name;
  int64_t batch, in_ch, out_ch, height, width, kernel;
  int pad;
};

// The full model (b = 64, I = 64, 1000 x 500 grid) and a small CPU model (b = 16, 0.2 m cells).
const Layer kLayers[] = {
    {"full_down1_64to128_250x500", 1, 64, 128, 250, 500, 3, 1},
    {"full_down2_128to256_125x250", 1, 128, 256, 125, 250, 3, 1},
    {"full_up1_512to256_62x125", 1, 512, 256, 62, 125, 3, 1},
    {"full_head_64to12_1x1_500x1000", 1, 64, 12, 500, 1000, 1, 0},
    {"small_down1_16to32_125x250_B2", 2, 16, 32, 125, 250, 3, 1},
    {"small_up4_48to16_250x500_B2", 2, 48, 16, 250, 500, 3, 1},
};

double flops_per_pass(const Layer& l) {
  return 2.0 * static_cast<double>(l.batch * l.out_ch * l.in_ch * l.kernel * l.kernel) *
         static_cast<double>(l.height * l.width);
}

TensorF random_tensor(const Shape& shape, uint64_t seed) {
  Rng rng(seed);
  TensorF t(shape);
  for (int64_t i = 0; i < t.numel(); ++i) t[i] = static_cast<float>(rng.uniform(-1.0, 1.0));
  return t;
}

void set_counters(benchmark::State& state, double flops_per_iteration) {
  state.counters["GFLOP/s"] =
      benchmark::Counter(flops_per_iteration * 1e-9, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["threads"] = num_threads();
}

void BM_Conv2dForward(benchmark::State& state, const Layer& l) {
  const TensorF x = random_tensor({l.batch, l.in_ch, l.height, l.width}, 1);
  const TensorF w = random_tensor({l.out_ch, l.in_ch, l.kernel, l.kernel}, 2);
  const TensorF bias = random_tensor({l.out_ch}, 3);
  TensorF y;
  for (auto _ : state) {
    host::conv2d_forward(x, w, &bias, l.pad, y);
    benchmark::DoNotOptimize(y.data());
  }
  set_counters(state, flops_per_pass(l));
}

void BM_Conv2dBackward(benchmark::State& state, const Layer& l) {
  const TensorF x = random_tensor({l.batch, l.in_ch, l.height, l.width}, 1);
  const TensorF w = random_tensor({l.out_ch, l.in_ch, l.kernel, l.kernel}, 2);
  const TensorF dy = random_tensor({l.batch, l.out_ch, l.height, l.width}, 4);
  TensorF dx, dw, db;
  for (auto _ : state) {
    host::conv2d_backward(x, w, dy, l.pad, &dx, &dw, &db);
    benchmark::DoNotOptimize(dx.data());
    benchmark::DoNotOptimize(dw.data());
  }
  set_counters(state, 2 * flops_per_pass(l));
}

void BM_GemmPeer(benchmark::State& state, const Layer& l) {
  using Matrix = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
  const int64_t depth = l.in_ch * l.kernel * l.kernel;
  const Matrix weights = Matrix::Random(l.out_ch, depth);
  const Matrix columns = Matrix::Random(depth, l.batch * l.height * l.width);
  Matrix out(l.out_ch, l.batch * l.height * l.width);
  for (auto _ : state) {
    out.noalias() = weights * columns;
    benchmark::DoNotOptimize(out.data());
  }
  set_counters(state, flops_per_pass(l));
}

int register_benchmarks() {
  for (const Layer& l : kLayers) {
    benchmark::RegisterBenchmark((std::string("Conv2dForward/") + l.name).c_str(), BM_Conv2dForward,
                                 l)
        ->Unit(benchmark::kMillisecond)
        ->UseRealTime();
    benchmark::RegisterBenchmark((std::string("Conv2dBackward/") + l.name).c_str(),
                                 BM_Conv2dBackward, l)
        ->Unit(benchmark::kMillisecond)
        ->UseRealTime();
    benchmark::RegisterBenchmark((std::string("GemmPeer/") + l.name).c_str(), BM_GemmPeer, l)
        ->Unit(benchmark::kMillisecond)
        ->UseRealTime();
  }
  return 0;
}

const int kRegistered = register_benchmarks();

}  // namespace

BENCHMARK_MAIN();
