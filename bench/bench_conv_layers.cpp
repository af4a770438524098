// The CPU backend's 3x3 convolutions, layer by layer, against the machine's GEMM rate, the host/
// reference and PyTorch's nn.Conv2d on the same shape and threads, in one run (PyTorch is
// bench/peer/pytorch_peer.py --serve in its own process, one layer step per command, alternating
// with ours). Benchmarks:
//   Gemm/4096/threads:T     C (4096 x 4096) = A * B in fp32 with Eigen: the machine's matrix-
//                           product rate; threads 1 is one Eigen call, threads T splits the
//                           rows of A over OpenMP (the build defines EIGEN_DONT_PARALLELIZE).
//   Conv3x3/<layer>         the CPU backend's 3x3 conv (Winograd) at each 3x3 conv shape of the
//                           full-size U-Nets, x (1, I, h, w) -> y (1, O, h, w).
// The table at the end gives each layer's ms, GFLOP/s (the direct convolution's FLOPs), its share
// of the GEMM's rate, the reference's ms and PyTorch's. Flags: bench/support/model_options.hpp
// (--layer_reps, --threads, --no_peer, --peer_python, --peer_script).
#include <benchmark/benchmark.h>
#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <numeric>
#include <optional>
#include <string>
#include <vector>

#include "bench/support/model_inputs.hpp"
#include "bench/support/model_layers.hpp"
#include "bench/support/model_options.hpp"
#include "bench/support/pytorch_peer.hpp"
#include "bench/support/report.hpp"
#include "bench/support/step_timing.hpp"
#include "core/eigen.hpp"
#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "core/ops.hpp"
#include "engine/cpu/bf16_conv.hpp"
#include "engine/backend/backend.hpp"
#include "engine/cpu/half_ops.hpp"
#include "host/conv2d.hpp"

using namespace pillarseg;
using namespace pillarseg::bench;

namespace {

// ---- results kept for the summary ----

// A rate by the wall clock and by the process's CPU time (GFLOP per CPU-second: a thread's
// rate when it has a core to itself, which a shared machine's load changes less).
struct Rate {
  double wall_gflops = 0.0, cpu_gflops = 0.0;
};
std::map<int, Rate> g_gemm;  // by thread count
struct LayerResult {
  std::string name, shape;
  double gflop = 0.0;
  StepTimes ours, reference, torch;  // ours: the CPU backend's fast path; reference: host/
  StepTimes bf16;                    // ours in BF16 (engine/cpu/bf16_conv), where the CPU has it:
                                     // the direct micro-kernel
  StepTimes bf16_winograd;           // and Winograd F(2x2, 3x3), the model's choice
  StepTimes amx_winograd;            // the same with its products on AMX-BF16 tiles, where present
};
std::vector<LayerResult> g_layers;
std::string g_layer_peer_note;
std::string g_bf16_note;  // why the BF16 column is empty
std::string g_amx_note;   // why the AMX column is empty

// ---- GEMM reference ----

constexpr int64_t kGemmSize = 4096;
// Work items of the threaded GEMM: blocks of rows of A (and C), each multiplied by all of B,
// scheduled dynamically. Measured here with 2 threads: 8 row blocks 174 GFLOP/s, 16 column
// blocks 140 (each column block packs all of A again).
constexpr int64_t kGemmRowBlocks = 8;

void BM_Gemm(benchmark::State& state, int threads) {
  using Matrix = Eigen::MatrixXf;
  const Matrix a = Matrix::Random(kGemmSize, kGemmSize);
  const Matrix b = Matrix::Random(kGemmSize, kGemmSize);
  Matrix c = Matrix::Zero(kGemmSize, kGemmSize);
  StepTimes t;
  for (auto _ : state) {
    state.SetIterationTime(time_once(t, [&] {
      if (threads == 1) {
        c.noalias() = a * b;
      } else {
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
        for (int64_t block = 0; block < kGemmRowBlocks; ++block) {
          const int64_t i0 = kGemmSize * block / kGemmRowBlocks;
          const int64_t i1 = kGemmSize * (block + 1) / kGemmRowBlocks;
          c.middleRows(i0, i1 - i0).noalias() = a.middleRows(i0, i1 - i0) * b;
        }
      }
      benchmark::DoNotOptimize(c.data());
    }));
  }
  const double flops =
      2.0 * static_cast<double>(kGemmSize * kGemmSize) * static_cast<double>(kGemmSize);
  set_rate_counters(state, flops, t);
  state.counters["threads"] = threads;
  g_gemm[threads] = {flops * 1e-9 / t.wall_median(), flops * 1e-9 / t.cpu_median()};
}

// ---- conv layers ----

TensorF random_tensor(const Shape& shape, uint64_t seed) {
  Rng rng(seed);
  TensorF t(shape);
  for (float& v : t) v = static_cast<float>(rng.uniform(-1.0, 1.0));
  return t;
}

// One peer process for all conv layers (started by the first, finished before the models).
std::optional<PeerProcess>& conv_peer() {
  static std::optional<PeerProcess> peer;
  return peer;
}

void finish_conv_peer() {
  std::optional<PeerProcess>& peer = conv_peer();
  if (!peer) return;
  peer->finish();
  if (!peer->ok()) g_layer_peer_note = peer->failure();
  peer.reset();
}

// Ours (the CPU backend's 3x3 convolution: Winograd, bias in its epilogue), the host/ reference
// and PyTorch's nn.Conv2d at one layer shape, alternating ours and PyTorch.
void BM_Conv3x3(benchmark::State& state, const Layer& l) {
  const TensorF x = random_tensor({l.batch, l.in, l.h, l.w}, 1);
  TensorF w = random_tensor({l.out, l.in, 3, 3}, 2);
  TensorF bias = random_tensor({l.out}, 3);
  TensorF y({l.batch, l.out, l.h, l.w});  // zero-filled: its pages are touched before timing
  TensorF y_reference({l.batch, l.out, l.h, l.w});
  const std::unique_ptr<Backend> backend = make_cpu_backend();
  const Ref x_ref{const_cast<float*>(x.data()), x.shape()}, w_ref{w.data(), w.shape()},
      bias_ref{bias.data(), bias.shape()};
  Ref y_ref{y.data(), y.shape()};
  // BF16: the weights prepared once (as the model does), the input rounded once, y in BF16.
  const bool bf16 = cpu::avx512_bf16_available(&g_bf16_note);
  const bool amx = cpu::amx_bf16_available(&g_amx_note);
  const Shape weight = w.shape();
  std::vector<uint16_t> w16(static_cast<size_t>(shape_numel(op::half16_conv_weights(weight, false))));
  std::vector<uint16_t> x16(static_cast<size_t>(x.numel())), y16(static_cast<size_t>(y.numel()));
  std::vector<float> bias16(static_cast<size_t>(l.out));
  HRef w16_ref{w16.data(), op::half16_conv_weights(weight, false)}, x16_ref{x16.data(), x.shape()};
  Ref bias16_ref{bias16.data(), {l.out}};
  cpu::Bf16WinogradWorkspace bf16_workspace;
  // And the Winograd-transformed weights, made once with them (as the model does) for each
  // kernel set.
  std::vector<uint16_t> u_avx512, u_amx;
  if (bf16) {
    cpu::prepare_conv_weights(Ref{w.data(), weight}, &bias_ref, nullptr, Precision::BF16, w16_ref,
                              bias16_ref);
    cpu::to_half(Ref{const_cast<float*>(x.data()), x.shape()}, Precision::BF16, x16_ref);
    u_avx512.resize(static_cast<size_t>(cpu::winograd_weight_elements(cpu::Bf16Kernels::Avx512, weight)));
    cpu::winograd_transform_weights(cpu::Bf16Kernels::Avx512, w16_ref, weight, u_avx512.data());
  }
  if (amx) {
    u_amx.resize(static_cast<size_t>(cpu::winograd_weight_elements(cpu::Bf16Kernels::Amx, weight)));
    cpu::winograd_transform_weights(cpu::Bf16Kernels::Amx, w16_ref, weight, u_amx.data());
  }
  if (options().peer && !conv_peer() && g_layer_peer_note.empty()) {
    conv_peer().emplace(std::vector<std::string>{"--case", "conv3x3"});
  }
  PeerProcess* peer = conv_peer() && conv_peer()->ok() ? &*conv_peer() : nullptr;
  const std::string command = fmt::format("conv3x3 {}:{}:{}:{}", l.in, l.out, l.h, l.w);
  LayerResult r{
      l.name, fmt::format("{} -> {} @ {}x{}", l.in, l.out, l.h, l.w), l.flops * 1e-9, {}, {}, {}, {}, {}, {}};
  int64_t pair = 0;
  for (auto _ : state) {
    // The order alternates so that a load rising or falling through the run weighs on both.
    const bool ours_first = pair++ % 2 == 0;
    if (peer && !ours_first) peer->step(command, r.torch);
    state.SetIterationTime(time_once(r.ours, [&] {
      backend->conv2d_forward(x_ref, w_ref, &bias_ref, 1, y_ref);
      benchmark::DoNotOptimize(y.data());
    }));
    if (peer && ours_first) peer->step(command, r.torch);
    time_once(r.reference, [&] {
      host::conv2d_forward(x, w, &bias, 1, y_reference);
      benchmark::DoNotOptimize(y_reference.data());
    });
    if (amx) {
      time_once(r.amx_winograd, [&] {
        cpu::conv3x3_winograd_forward(cpu::Bf16Kernels::Amx, x16_ref, w16_ref, u_amx.data(), bias16_ref, weight,
                                      false, TensorRef{y16.data(), y.shape(), DType::BF16}, bf16_workspace);
        benchmark::DoNotOptimize(y16.data());
      });
    }
    if (bf16) {
      time_once(r.bf16, [&] {
        cpu::conv2d_forward(cpu::Bf16Kernels::Avx512, x16_ref, w16_ref, bias16_ref, weight, 1, false,
                            TensorRef{y16.data(), y.shape(), DType::BF16});
        benchmark::DoNotOptimize(y16.data());
      });
      time_once(r.bf16_winograd, [&] {
        cpu::conv3x3_winograd_forward(cpu::Bf16Kernels::Avx512, x16_ref, w16_ref, u_avx512.data(), bias16_ref,
                                      weight, false, TensorRef{y16.data(), y.shape(), DType::BF16}, bf16_workspace);
        benchmark::DoNotOptimize(y16.data());
      });
    }
  }
  if (peer && !peer->ok()) finish_conv_peer();
  set_rate_counters(state, l.flops, r.ours);
  set_peer_counters(state, r.ours, r.torch);
  g_layers.push_back(std::move(r));
}

// The 3x3 conv layers of the full-size U-Nets, bilinear first, then the transposed variant's
// shapes that the bilinear one does not have; x (1, I, h, w) -> (1, O, h, w).
std::vector<Layer> conv3x3_layers() {
  std::vector<Layer> all;
  for (bool transposed : {false, true}) {
    for (Layer l : forward_layers(config_of("full", transposed), 1, 0)) {
      if (l.kind != Layer::Kind::Conv || l.k != 3) continue;
      const bool seen = std::any_of(all.begin(), all.end(), [&](const Layer& o) {
        return o.in == l.in && o.out == l.out && o.h == l.h && o.w == l.w;
      });
      if (seen) continue;
      l.name = (transposed ? "T:" : "") +
               l.name.substr(l.name.find('.') + 1);  // drop segmentation_head.
      all.push_back(l);
    }
  }
  return all;
}

// ---- summary ----

void print_gemm_and_layers() {
  if (!g_gemm.empty()) {
    fmt::print("\nGEMM 4096^3 fp32 (Eigen), GFLOP/s by the wall clock and GFLOP per CPU-second:\n");
    for (const auto& [threads, rate] : g_gemm) {
      fmt::print("  {} thread(s): {:.1f} GFLOP/s, {:.1f} GFLOP/cpu-s\n", threads, rate.wall_gflops,
                 rate.cpu_gflops);
    }
  }
  if (g_layers.empty()) return;
  const auto gemm = g_gemm.find(num_threads());
  const auto share = [&](double rate, bool by_cpu) {
    if (gemm == g_gemm.end()) return std::string("-");
    const double gemm_rate = by_cpu ? gemm->second.cpu_gflops : gemm->second.wall_gflops;
    return fmt::format("{:.0f}%", 100.0 * rate / gemm_rate);
  };
  fmt::print(
      "\n3x3 conv layers, the CPU backend's conv2d_forward (Winograd F(4x4,3x3)), batch 1, {} "
      "threads, median of {}: ms, GFLOP/s, CPU ms, GFLOP per CPU-s, % of the {}-thread GEMM's "
      "rate by wall and by CPU time (GFLOP: the direct convolution's 2 O I 9 h w, so Winograd's "
      "fewer multiplies show as a higher rate); the host/ reference (im2col + GEMM) ms; PyTorch's "
      "nn.Conv2d run in turn, and the median step ratio ours / torch (wall, CPU); ours in BF16 "
      "(BF16 in and out, AVX512_BF16: the direct micro-kernel, and Winograd F(2x2, 3x3) as the model runs "
      "it) ms and fp32 ms / Winograd bf16 ms; the BF16 Winograd with its products on AMX-BF16 tiles ms:\n",
      num_threads(), options().layer_reps, num_threads());
  fmt::print(
      "  {:<30} {:>22} {:>7} {:>7} {:>7} {:>8} {:>6} {:>6} | {:>7} | {:>8} {:>7} | {:>5} {:>5} | {:>7} {:>7} {:>5} "
      "{:>7}\n",
      "layer", "I -> O @ h x w", "ms", "GFLOP/s", "CPU ms", "GF/cpu-s", "%wall", "%CPU", "ref ms",
      "torch ms", "CPU ms", "wall", "CPU", "bf16 ms", "wino ms", "x", "amx ms");
  for (const LayerResult& l : g_layers) {
    const double wall_rate = l.gflop / l.ours.wall_median(),
                 cpu_rate = l.gflop / l.ours.cpu_median();
    fmt::print(
        "  {:<30} {:>22} {:>7.0f} {:>7.1f} {:>7.0f} {:>8.1f} {:>6} {:>6} | {:>7.0f} | {:>8} {:>7} "
        "| {:>5} {:>5} | {:>7} {:>7} {:>5} {:>7}\n",
        l.name, l.shape, l.ours.wall_median() * 1e3, wall_rate, l.ours.cpu_median() * 1e3, cpu_rate,
        share(wall_rate, false), share(cpu_rate, true), l.reference.wall_median() * 1e3,
        fixed(wall_ms(l.torch), 0),
        fixed(cpu_ms(l.torch), 0), ratio(l.ours.wall, l.torch.wall),
        ratio(l.ours.cpu, l.torch.cpu), fixed(wall_ms(l.bf16), 0), fixed(wall_ms(l.bf16_winograd), 0),
        ratio(l.ours.wall, l.bf16_winograd.wall), fixed(wall_ms(l.amx_winograd), 1));
  }
  if (!g_layer_peer_note.empty()) fmt::print("  PyTorch: {}\n", g_layer_peer_note);
  if (!g_bf16_note.empty()) fmt::print("  BF16: not run: {}\n", g_bf16_note);
  if (!g_amx_note.empty()) fmt::print("  AMX-BF16 (amx ms): not run: {}\n", g_amx_note);
}

// ---- registration ----

void register_benchmarks() {
  const int threads = num_threads();
  for (int t : threads == 1 ? std::vector<int>{1} : std::vector<int>{1, threads}) {
    benchmark::RegisterBenchmark(fmt::format("Gemm/{}/threads:{}", kGemmSize, t).c_str(), BM_Gemm,
                                 t)
        ->Iterations(options().layer_reps)
        ->UseManualTime()
        ->Unit(benchmark::kMillisecond);
  }
  for (const Layer& l : conv3x3_layers()) {
    benchmark::RegisterBenchmark(
        fmt::format("Conv3x3/{}/{}to{}/{}x{}", l.name, l.in, l.out, l.h, l.w).c_str(), BM_Conv3x3,
        l)
        ->Iterations(options().layer_reps)
        ->UseManualTime()
        ->Unit(benchmark::kMillisecond);
  }
}

}  // namespace

int main(int argc, char** argv) {
  const auto report = [] {
    finish_conv_peer();
    print_gemm_and_layers();
  };
  return model_benchmark_main(argc, argv, "bench_conv_layers", register_benchmarks, report,
                              finish_conv_peer);
}
