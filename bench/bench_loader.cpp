// The data loader's work (train.workers, engine/train/prefetcher.hpp): the time to prepare one
// augmented training sample (read the scan, augment, ground truth, the observability or 3D
// occupancy of the augmented scan or the grid-map layers, pillars and their decoration) for each
// of the paper's configs (configs/*.yaml at full size: pillar, pillar + 2D, pillar + 3D, the
// grid-map baseline; sparse and dense), on one thread, over a simulated 6-scan sequence written
// once to a temporary directory (dense ground truth cached before timing, as training does).
// Counter: ms_per_sample; with the step time of a run it says how many workers keep the step fed.
#include <benchmark/benchmark.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "core/classes.hpp"
#include "core/parallel.hpp"
#include "engine/model/run_config.hpp"
#include "engine/pipeline/dataset.hpp"
#include "engine/sim/simulate.hpp"

using namespace pillarseg;
namespace fs = std::filesystem;

namespace {

constexpr int kScans = 6;

const fs::path& data_root() {
  static const fs::path root = [] {
    const fs::path dir =
        fs::temp_directory_path() / ("pillarseg_bench_loader." + std::to_string(::getpid()));
    fs::remove_all(dir);
    sim::SimulateOptions o;
    o.out = dir;
    o.sequences = 1;
    o.scans = kScans;
    o.seed = 11;
    sim::simulate(o);
    return dir;
  }();
  return root;
}

void BM_PrepareSample(benchmark::State& state, const std::string& config_name) {
  const RunConfig cfg =
      load_run_config(fs::path(PILLARSEG_SOURCE_DIR) / "configs" / (config_name + ".yaml"));
  TrainConfig tc = cfg.train;
  tc.sequences = {0};
  const bool dense = tc.ground_truth == GroundTruthKind::dense;
  const fs::path cache = data_root() / ("cache_" + config_name);
  const ScanDataset data(data_root(), tc.sequences, 1, 0, cfg.model, ClassTable::defaults(),
                         tc.ground_truth, cache, dense && tc.augment);
  ScopedThreads one(1);
  if (dense) data.build_cache(GroundTruthKind::dense);
  size_t i = 0;
  uint64_t epoch = 0;
  double seconds = 0;
  for (auto _ : state) {
    const auto started = std::chrono::steady_clock::now();
    Sample s = data.training_sample(i, epoch, tc);
    benchmark::DoNotOptimize(s.labels.data());
    seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
    if (++i == data.size()) i = 0, ++epoch;
  }
  state.counters["ms_per_sample"] = 1e3 * seconds / static_cast<double>(state.iterations());
}

}  // namespace

int main(int argc, char** argv) {
  for (const char* name :
       {"pillar_sparse", "pillar_2d_sparse", "pillar_3d_sparse", "gridmap_sparse", "pillar_dense",
        "pillar_2d_dense", "pillar_3d_dense"}) {
    benchmark::RegisterBenchmark((std::string("PrepareSample/") + name).c_str(), BM_PrepareSample,
                                 std::string(name))
        ->Unit(benchmark::kMillisecond)
        ->MinTime(1.0);
  }
  benchmark::Initialize(&argc, argv);
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  fs::remove_all(data_root());
  return 0;
}
