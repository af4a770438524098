#include "bench/support/model_inputs.hpp"

#include <fmt/format.h>
#include <unistd.h>

#include <algorithm>
#include <map>
#include <vector>

#include "bench/support/model_options.hpp"
#include "core/classes.hpp"
#include "core/error.hpp"
#include "core/io.hpp"
#include "engine/data/ground_truth.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/sim/simulate.hpp"
#include "host/pillar_gather.hpp"
#include "host/point_decoration.hpp"

namespace pillarseg::bench {

ModelConfig config_of(const std::string& size, bool transposed) {
  ModelConfig c;  // the paper's full size
  if (size == "small") {  // configs/small_cpu.yaml's network (make demo)
    c.grid.cell = 0.4;
    c.pillar_channels = 32;
    c.base_width = 16;
  }
  c.transposed = transposed;
  return c;
}

namespace {

// Sample b of a batch: simulated scan b of one street of `batch` scans, or the --scan file with
// its labels.
Scan input_scan(int b, int batch) {
  if (options().scan.empty()) {
    sim::SimScan simulated = sim::SequenceSimulator(kSimulatorSeed, batch).scan(b);
    Scan scan;
    scan.points = std::move(simulated.points);
    scan.labels = std::move(simulated.labels);
    return scan;
  }
  const std::filesystem::path labels = options().scan.parent_path().parent_path() / "labels" /
                                       options().scan.filename().replace_extension(".label");
  PS_CHECK(std::filesystem::exists(labels),
           "--scan={}: the training step needs its labels, expected in {}", options().scan.string(),
           labels.string());
  return read_scan(options().scan, labels);
}

// Scans 0..batch-1 -> all their non-empty pillars (inference subsampling to N points),
// decorated, in one batch; labels: each scan's sparse ground truth.
SizeSetup make_setup(const std::string& size) {
  SizeSetup s;
  s.size = size;
  s.config = config_of(size, false);
  s.batch = size == "small" ? 2 : 1;
  const GridSpec& grid = s.config.grid;
  const int N = s.config.max_points_per_pillar, H = grid.height(), W = grid.width();
  std::vector<float> points;
  std::vector<int32_t> cells;
  s.labels = Tensor<uint8_t>({s.batch, H, W});
  for (int b = 0; b < s.batch; ++b) {
    const Scan scan = input_scan(b, s.batch);
    const host::Pillars pillars =
        host::pillar_gather(scan.points, grid, {N, 0}, host::SampleMode::Inference, nullptr);
    const Tensor<float> decorated = host::decorate_points(scan.points, pillars, grid);
    points.insert(points.end(), decorated.data(), decorated.data() + decorated.numel());
    for (int64_t p = 0; p < pillars.num_pillars(); ++p) {
      cells.insert(cells.end(), {b, pillars.cell(p, 0), pillars.cell(p, 1)});
    }
    const Tensor<uint8_t> map = sparse_ground_truth(scan, ClassTable::defaults(), grid);
    std::copy(map.data(), map.data() + map.numel(), s.labels.data() + int64_t{b} * H * W);
  }
  const int64_t P = static_cast<int64_t>(cells.size() / 3);
  s.inputs.batch = s.batch;
  s.inputs.pillar_points = Tensor<float>({P, N, 10});
  std::copy(points.begin(), points.end(), s.inputs.pillar_points.data());
  s.inputs.pillar_cells = Tensor<int32_t>({P, 3});
  std::copy(cells.begin(), cells.end(), s.inputs.pillar_cells.data());

  s.peer_inputs = std::filesystem::temp_directory_path() /
                  fmt::format("pillarseg_bench_model_{}_{}", getpid(), size);
  const auto write = [&](const char* file, const auto& t) {
    write_file_atomic(s.peer_inputs / file, t.data(),
                      static_cast<size_t>(t.numel()) * sizeof(*t.data()));
  };
  write("points.f32", s.inputs.pillar_points);
  write("cells.i32", s.inputs.pillar_cells);
  write("labels.u8", s.labels);
  return s;
}

std::map<std::string, SizeSetup>& setups() {
  static std::map<std::string, SizeSetup> all;
  return all;
}

}  // namespace

const SizeSetup& setup(const std::string& size) {
  auto it = setups().find(size);
  if (it == setups().end()) it = setups().emplace(size, make_setup(size)).first;
  return it->second;
}

void remove_peer_inputs() {
  for (const auto& [size, s] : setups()) std::filesystem::remove_all(s.peer_inputs);
}

}  // namespace pillarseg::bench
