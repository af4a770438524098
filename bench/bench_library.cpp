// The library's steady-state latency: pillarseg_segment through libpillarseg.so (the C API a
// user links) against the engine's ScanSegmenter::segment (what `pillarseg bench` times) on the
// same model, scan and threads, alternating call by call in one run, with the median per-call
// ratio (1.0: the C API adds nothing). The model: the paper's full size with random weights (a
// checkpoint written to a temporary file), or --config's. Benchmarks:
//   Segment/capi       pillarseg_segment, labels only
//   Segment/engine     ScanSegmenter::segment, labels only
// Own flags: --scan=PATH (a point file: .bin, .pcd, .ply, .npy, .pcd.bin; default: a simulated
// 120k-point scan), --config=RUN.yaml, --device=cpu|emu|cuda, --threads=T (0: all).
#include <benchmark/benchmark.h>
#include <fmt/format.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "core/parallel.hpp"
#include "engine/cuda/install.hpp"
#include "engine/data/point_formats.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/pipeline/segmenter.hpp"
#include "engine/sim/simulate.hpp"
#include "pillarseg/pillarseg.h"

using namespace pillarseg;

namespace {

using Clock = std::chrono::steady_clock;

struct Options {
  std::filesystem::path scan, config;
  std::string device = "cpu";
  int threads = 0;
};

Options parse_options(int& argc, char** argv) {
  Options o;
  int kept = 1;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg.rfind("--scan=", 0) == 0) {
      o.scan = arg.substr(7);
    } else if (arg.rfind("--config=", 0) == 0) {
      o.config = arg.substr(9);
    } else if (arg.rfind("--device=", 0) == 0) {
      o.device = arg.substr(9);
    } else if (arg.rfind("--threads=", 0) == 0) {
      o.threads = std::stoi(arg.substr(10));
    } else {
      argv[kept++] = argv[i];
    }
  }
  argc = kept;
  return o;
}

double median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

// Both sides of the comparison, made once.
struct Sides {
  std::filesystem::path checkpoint;
  std::vector<Point> points;
  std::vector<float> xyzr;
  std::unique_ptr<ScanSegmenter> engine;
  pillarseg_segmenter* capi = nullptr;
  std::vector<uint8_t> labels;
  std::vector<double> engine_ms, capi_ms;

  ~Sides() {
    pillarseg_close(capi);
    std::error_code ec;
    std::filesystem::remove(checkpoint, ec);
  }
};

Sides& sides(const Options& o) {
  static const std::unique_ptr<Sides> s = [&] {
    auto owned = std::make_unique<Sides>();
    Sides& made = *owned;
    const RunConfig config = o.config.empty() ? parse_run_config("", "the paper's settings") : load_run_config(o.config);
    made.checkpoint = std::filesystem::temp_directory_path() / fmt::format("pillarseg_bench_library_{}.safetensors", getpid());
    {
      auto backend = make_cpu_backend();
      PillarSegNet net(config.model, *backend, 1);
      save_checkpoint(made.checkpoint, net, config, {}, false);
    }
    if (o.scan.empty()) {
      made.points = sim::SequenceSimulator(sim::sequence_seed(1, 0), 1).scan(0).points;
    } else {
      made.points = read_points(o.scan).points;
    }
    for (const Point& p : made.points) made.xyzr.insert(made.xyzr.end(), {p.x, p.y, p.z, p.r});
    install_emulated_cuda_backend();
#if defined(PILLARSEG_WITH_CUDA_BACKEND)
    install_cuda_backend();
#endif
    SegmenterOptions so;
    so.device = o.device;
    so.threads = o.threads;
    made.engine = open_segmenter(made.checkpoint, "", so);
    pillarseg_options co;
    pillarseg_default_options(&co);
    co.device = o.device.c_str();
    co.threads = o.threads;
    char error[512];
    made.capi = pillarseg_open(made.checkpoint.string().c_str(), nullptr, &co, error, sizeof error);
    if (!made.capi) throw Error(error);
    made.labels.resize(static_cast<size_t>(config.model.grid.cells()));
    return owned;
  }();
  return *s;
}

Options g_options;

double time_engine(Sides& s) {
  const auto t0 = Clock::now();
  s.engine->segment(s.points, s.labels.data());
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

double time_capi(Sides& s) {
  char error[512];
  const auto t0 = Clock::now();
  if (pillarseg_segment(s.capi, s.xyzr.data(), s.points.size(), s.labels.data(), nullptr, error, sizeof error) != 0)
    throw Error(error);
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

// Alternating: this side, then the other, each call timed; this side's times are the benchmark's.
void BM_Segment(benchmark::State& state, bool capi) {
  Sides& s = sides(g_options);
  time_engine(s), time_capi(s);  // warm-up: plans, records
  for (auto _ : state) {
    const double mine = capi ? time_capi(s) : time_engine(s);
    const double other = capi ? time_engine(s) : time_capi(s);
    state.SetIterationTime(mine * 1e-3);
    (capi ? s.capi_ms : s.engine_ms).push_back(mine);
    (capi ? s.engine_ms : s.capi_ms).push_back(other);
  }
  state.counters["median_ms"] = median(capi ? s.capi_ms : s.engine_ms);
  state.counters["points"] = static_cast<double>(s.points.size());
}

}  // namespace

int main(int argc, char** argv) {
  try {
    g_options = parse_options(argc, argv);
    set_num_threads(g_options.threads);
    benchmark::Initialize(&argc, argv);
    if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
    for (const bool capi : {true, false}) {
      benchmark::RegisterBenchmark(capi ? "Segment/capi" : "Segment/engine", BM_Segment, capi)
          ->Iterations(5)
          ->UseManualTime()
          ->Unit(benchmark::kMillisecond);
    }
    benchmark::RunSpecifiedBenchmarks();
    Sides& s = sides(g_options);
    std::vector<double> ratios;
    for (size_t i = 0; i < std::min(s.capi_ms.size(), s.engine_ms.size()); ++i) ratios.push_back(s.capi_ms[i] / s.engine_ms[i]);
    fmt::print("\nC API (libpillarseg.so) against the engine's segmenter, {} points, device {}, {} threads: median "
               "{:.1f} ms against {:.1f} ms, median per-call ratio {:.3f}\n",
               s.points.size(), s.engine->backend().name(), num_threads(), median(s.capi_ms), median(s.engine_ms),
               median(ratios));
    benchmark::Shutdown();
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_library: %s\n", e.what());
    return 1;
  }
  return 0;
}
