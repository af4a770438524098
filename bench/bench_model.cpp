// PillarSegNet on the CPU (engine/model on the CpuBackend) against PyTorch on the same network,
// input and thread count, in one run. This machine is shared and its load drifts, so every
// comparison alternates the two sides step by step (ours then PyTorch, then PyTorch then ours)
// and reports the median of the per-step ratios. PyTorch is bench/peer/pytorch_peer.py --serve
// run by /usr/bin/python3 in its own process, one step per command on its stdin. Benchmarks:
//   Model/<size>/<variant>/<forward|train>
//                           forward: eval mode (PyTorch: under no_grad); train: training-mode
//                           forward + weighted cross-entropy + backward + gradient-norm clip 10
//                           + Adam(W) step; PyTorch reads the same pillars and labels, written
//                           to a temporary directory.
// Sizes: full = the paper's (grid 1000 x 500 cells of 0.1 m, C = b = 64, depth 4, batch 1);
// small (--small) = the CPU configs' (0.4 m cells: 250 x 125, C = 32, b = 16, batch 2). Variants:
// bilinear (the authors' UNet(64, 12)) and transposed. Input: simulated scans (engine/sim:
// 64-beam LiDAR in a procedural street), or a labelled SemanticKITTI scan given with --scan,
// -> every non-empty pillar, N = 20 points, decorated (P, N, 10); labels: the sparse ground
// truth (B, H, W).
// FLOPs: 2 x the multiply-adds of every conv, transposed conv and linear layer of one forward,
// the op records' counts over the model's evaluation graph (bench/support/model_layers.hpp, the
// figures of `pillarseg bench --ops`); a training step counts 3 x that (each layer's backward
// computes dx and dw, each as many multiply-adds as its forward).
// Each model case: one warm-up step on each side, then --reps timed steps each; reported:
// median wall ms, GFLOP/s at it, the median process CPU time of a step (all threads: on a
// shared machine it varies less with the load than the wall time does), and the peak RSS of
// the case (ours: getrusage ru_maxrss after resetting the process's high-water mark through
// /proc/self/clear_refs; PyTorch: VmHWM of its own process). Tables at the end: ours vs PyTorch,
// where our time goes per op of the model's op graph (PillarSegNet::set_op_timing) and in the
// optimiser, and, with
// --peer_profile, where PyTorch's goes. The per-layer comparison is bench_conv_layers.
//
// Flags: bench/support/model_options.hpp.
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
#include "core/parallel.hpp"
#include "engine/backend/backend.hpp"
#include "engine/model/pillarsegnet.hpp"

using namespace pillarseg;
using namespace pillarseg::bench;

namespace {

constexpr double kGradClip = 10.0;

// ---- results kept for the summary ----

struct CaseResult {
  double gflop = 0.0;
  int64_t params = 0, pillars = 0;
  StepTimes ours, torch;
  std::optional<double> ours_rss_mb, torch_rss_mb;
  std::map<std::string, PillarSegNet::OpTime> ours_ops;  // mean per step
  std::string peer_note, peer_profile;
};

struct ModelCase {
  std::string size;
  bool transposed = false;
  bool training = false;
  std::string key() const {
    return fmt::format("{} {} {}", size, transposed ? "transposed" : "bilinear",
                       training ? "train" : "forward");
  }
};

std::map<std::string, CaseResult> g_cases;  // by ModelCase::key()
// ---- the model ----

// The optimiser's part of a training step (clip + Adam), outside the op graph: its time is added
// to the model's op times under this name.
constexpr const char* kOptimizerOp = "optimizer: clip + adam";

// One step: eval forward, or training forward + loss + backward + clip + Adam (timed into
// optimizer when given).
void model_step(PillarSegNet& net, Backend& backend, const SizeSetup& s, bool training,
                int64_t& adam_steps, PillarSegNet::OpTime* optimizer = nullptr) {
  if (!training) {
    net.forward(s.inputs, false);
    return;
  }
  net.forward(s.inputs, true);
  net.loss(s.labels, LossKind::CrossEntropy, kCoefficients);
  net.backward();
  const double start = backend.clock_ms();
  ParameterSet& ps = net.parameters();
  Ref grads = ps.grads();
  const double norm = std::sqrt(backend.sum_of_squares(grads));
  if (norm > kGradClip) backend.scale(grads, static_cast<float>(kGradClip / (norm + 1e-6)));
  AdamOptions adam;
  adam.beta2 = 0.99;  // the paper's
  Ref values = ps.values(), m = ps.adam_m(), v = ps.adam_v();
  backend.adam_step(values, grads, m, v, ++adam_steps, adam);
  if (optimizer) {
    optimizer->ms += backend.clock_ms() - start;
    ++optimizer->calls;
  }
}

std::vector<std::string> peer_model_arguments(const ModelCase& c, const SizeSetup& s) {
  const ModelConfig config = config_of(c.size, c.transposed);
  std::vector<std::string> args{"--case",
                                c.training ? "train" : "forward",
                                "--variant",
                                c.transposed ? "transposed" : "bilinear",
                                "--batch",
                                std::to_string(s.batch),
                                "--height",
                                std::to_string(config.grid.height()),
                                "--width",
                                std::to_string(config.grid.width()),
                                "--pillar-channels",
                                std::to_string(config.pillar_channels),
                                "--base-width",
                                std::to_string(config.base_width),
                                "--depth",
                                std::to_string(config.depth),
                                "--points-per-pillar",
                                std::to_string(config.max_points_per_pillar),
                                "--inputs",
                                s.peer_inputs.string()};
  if (options().peer_profile) args.push_back("--profile");
  return args;
}

// Ours and PyTorch (its own process, warmed up first), one step each in turn.
void BM_Model(benchmark::State& state, const ModelCase& c) {
  const SizeSetup& s = setup(c.size);
  CaseResult& r = g_cases[c.key()];
  std::optional<PeerProcess> peer;
  if (options().peer) peer.emplace(peer_model_arguments(c, s));
  const bool rss_reset = reset_peak_rss();
  const std::unique_ptr<Backend> backend_owner = make_cpu_backend();
  Backend& backend = *backend_owner;
  PillarSegNet net(config_of(c.size, c.transposed), backend, /*seed=*/1);
  const double step_flops =
      (c.training ? 3.0 : 1.0) *
      total_flops(forward_layers(net.config(), s.batch, s.inputs.pillar_points.dim(0)));
  int64_t adam_steps = 0;
  model_step(net, backend, s, c.training,
             adam_steps);  // warm-up: plans and first-touches the arenas
  net.set_op_timing(true);
  PillarSegNet::OpTime optimizer;
  int64_t pair = 0;
  for (auto _ : state) {
    // The order alternates so that a load rising or falling through the run weighs on both.
    const bool ours_first = pair++ % 2 == 0;
    if (peer && !ours_first) peer->step("step", r.torch);
    state.SetIterationTime(time_once(
        r.ours, [&] { model_step(net, backend, s, c.training, adam_steps, &optimizer); }));
    if (peer && ours_first) peer->step("step", r.torch);
  }
  const double rss = peak_rss_mb();
  r.gflop = step_flops * 1e-9;
  r.params = net.parameters().num_trainable();
  r.pillars = s.inputs.pillar_points.dim(0);
  if (rss_reset) r.ours_rss_mb = rss;
  const double steps = static_cast<double>(r.ours.wall.size());
  std::map<std::string, PillarSegNet::OpTime> totals = net.op_times();
  if (optimizer.calls > 0) totals[kOptimizerOp] = optimizer;
  for (auto [op, total] : totals) {
    total.ms /= steps, total.flops /= steps;
    total.calls = static_cast<int64_t>(static_cast<double>(total.calls) / steps);
    r.ours_ops[op] = total;
  }
  set_rate_counters(state, step_flops, r.ours);
  state.counters["peak_RSS_MB"] = rss;
  state.counters["pillars"] = static_cast<double>(r.pillars);
  if (!peer) return;
  peer->finish();
  if (!peer->ok()) {
    r.peer_note = peer->failure();
    return;
  }
  set_peer_counters(state, r.ours, r.torch);
  const auto fields = parse_fields(peer->summary());
  r.torch_rss_mb = std::stod(fields.at("peak_rss_mb"));
  for (const std::string& line : peer->lines()) {
    if (line.rfind("PEER_PROFILE ", 0) == 0) r.peer_profile += "  " + line.substr(13) + "\n";
  }
  // The same network and input on both sides: parameter and FLOP counts must agree.
  const int64_t peer_params = std::stoll(fields.at("params"));
  const double peer_gflop = std::stod(fields.at("gflop"));
  if (peer_params != r.params || std::abs(peer_gflop - r.gflop) > 0.01 * r.gflop) {
    r.peer_note =
        fmt::format("MISMATCH: PyTorch has {} parameters and {:.2f} GFLOP, ours {} and {:.2f}",
                    peer_params, peer_gflop, r.params, r.gflop);
  }
}

// ---- summary ----

void print_cases() {
  if (g_cases.empty()) return;
  fmt::print(
      "\nPillarSegNet on the CPU, {} threads, ours and PyTorch one step each in turn, median of {} "
      "after one warm-up: wall ms, GFLOP/s, process CPU ms (all threads), peak RSS MB; the median "
      "step ratio ours / torch (> 1: ours slower) by wall and by CPU time:\n",
      num_threads(), options().reps);
  fmt::print(
      "  {:<26} {:>7} {:>7} | {:>8} {:>7} {:>7} {:>7} | {:>8} {:>7} {:>7} {:>7} | {:>5} {:>5}\n",
      "case", "pillars", "GFLOP", "ours ms", "GFLOP/s", "CPU ms", "RSS MB", "torch ms", "GFLOP/s",
      "CPU ms", "RSS MB", "wall", "CPU");
  for (const auto& [key, r] : g_cases) {
    const auto rate = [&](const StepTimes& t) {
      return t.wall.empty() ? std::string("-") : fmt::format("{:.1f}", r.gflop / t.wall_median());
    };
    fmt::print(
        "  {:<26} {:>7} {:>7.1f} | {:>8} {:>7} {:>7} {:>7} | {:>8} {:>7} {:>7} {:>7} | {:>5} "
        "{:>5}\n",
        key, r.pillars, r.gflop, fixed(wall_ms(r.ours), 0), rate(r.ours), fixed(cpu_ms(r.ours), 0),
        fixed(r.ours_rss_mb, 0), fixed(wall_ms(r.torch), 0), rate(r.torch),
        fixed(cpu_ms(r.torch), 0), fixed(r.torch_rss_mb, 0), ratio(r.ours.wall, r.torch.wall),
        ratio(r.ours.cpu, r.torch.cpu));
    fmt::print("  {:<26} wall ms of each step: ours {}  torch {}\n", "", wall_list(r.ours),
               wall_list(r.torch));
    if (!r.peer_note.empty()) fmt::print("  {:<26} {}\n", "", r.peer_note);
  }
  for (const auto& [key, r] : g_cases) {
    if (r.ours_ops.empty()) continue;
    const double mean_ms = 1e3 * std::accumulate(r.ours.wall.begin(), r.ours.wall.end(), 0.0) /
                           static_cast<double>(r.ours.wall.size());
    fmt::print("\nWhere our time goes: {} (mean of the timed steps: {:.0f} ms)\n", key, mean_ms);
    fmt::print("  {:<30} {:>7} {:>10} {:>7} {:>9}\n", "op", "calls", "ms/step", "share", "GFLOP/s");
    std::vector<std::pair<std::string, PillarSegNet::OpTime>> ops(r.ours_ops.begin(),
                                                                  r.ours_ops.end());
    std::sort(ops.begin(), ops.end(),
              [](const auto& a, const auto& b) { return a.second.ms > b.second.ms; });
    double accounted_ms = 0.0;
    for (const auto& [op, t] : ops) {
      accounted_ms += t.ms;
      const std::string op_rate = t.flops > 0 ? fmt::format("{:.1f}", t.flops * 1e-6 / t.ms) : "";
      fmt::print("  {:<30} {:>7} {:>10.1f} {:>6.1f}% {:>9}\n", op, t.calls, t.ms,
                 100.0 * t.ms / mean_ms, op_rate);
    }
    fmt::print("  {:<30} {:>7} {:>10.1f}\n", "(uploads, the model's own code)", "",
               mean_ms - accounted_ms);
  }
  for (const auto& [key, r] : g_cases) {
    if (r.peer_profile.empty()) continue;
    fmt::print("\nWhere PyTorch's time goes: {} (one more step, torch.profiler)\n{}", key,
               r.peer_profile);
  }
}

// ---- registration ----

void register_benchmarks() {
  std::vector<std::string> sizes{"full"};
  if (options().small) sizes.insert(sizes.begin(), "small");
  for (const std::string& size : sizes) {
    for (bool transposed : {false, true}) {
      for (bool training : {false, true}) {
        const ModelCase c{size, transposed, training};
        benchmark::RegisterBenchmark(
            fmt::format("Model/{}/{}/{}", size, transposed ? "transposed" : "bilinear",
                        training ? "train" : "forward")
                .c_str(),
            BM_Model, c)
            ->Iterations(options().reps)
            ->UseManualTime()
            ->Unit(benchmark::kMillisecond);
      }
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  return model_benchmark_main(argc, argv, "bench_model", register_benchmarks, print_cases,
                              remove_peer_inputs);
}
