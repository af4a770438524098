// pillarseg bench: the stage breakdown of one inference on a real-size scan (read, pillarize,
// input maps, upload, PFN, scatter, occupancy stream, U-Net, head, write: argmax + label map),
// median over repetitions, the total, and the process's peak resident memory. Stages the config
// does not have (input maps, occupancy stream) are not listed. Network stages are timed on the
// backend's clock (CUDA events with --device cuda); where the backend records graphs, the
// forward is also timed as one graph replay (stage timing waits between stages, so the
// breakdown itself runs uncaptured).
#include <fmt/format.h>
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <filesystem>

#include "core/parallel.hpp"
#include "engine/cli/commands.hpp"
#include "engine/data/ground_truth.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "engine/pipeline/scan_inputs.hpp"
#include "engine/render/label_map.hpp"
#include "engine/sim/simulate.hpp"
#include "engine/train/checkpoint.hpp"

namespace pillarseg::cli {

namespace {

struct BenchArgs {
  std::string device = "cpu", conv = "own", config, weights, scan;
  int repeat = 5;
  bool transposed = false;
};

double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

void run_bench(const BenchArgs& a) {
  namespace fs = std::filesystem;
  ModelConfig model;
  if (!a.config.empty()) model = load_run_config(a.config).model;
  model.transposed = model.transposed || a.transposed;
  auto backend = make_backend(a.device, a.conv);  // first: no device, no scratch files left behind
  const fs::path scratch = fs::temp_directory_path() / fmt::format("pillarseg_bench_{}", ::getpid());
  fs::path scan_path = a.scan;
  if (scan_path.empty()) {
    // A simulated real-size scan (about 120k points).
    sim::SequenceSimulator simulator(sim::sequence_seed(1, 0), 1);
    scan_path = scratch / "scan.bin";
    write_bin(scan_path, simulator.scan(0).points);
  }
  PillarSegNet net(model, *backend);
  if (!a.weights.empty()) load_weights(read_checkpoint(a.weights), net, false);
  net.set_stage_timing(true);
  const ClassTable classes = ClassTable::defaults();

  std::vector<std::string> names = {"read", "pillarize", "input maps", "upload", "PFN", "scatter", "occupancy",
                                    "U-Net", "head", "write", "total"};
  const bool has_maps = model.occupancy != OccupancyInput::None || model.grid_map_input;
  const auto listed = [&](size_t stage) {
    return (names[stage] != "input maps" || has_maps) &&
           (names[stage] != "occupancy" || model.occupancy != OccupancyInput::None);
  };
  std::vector<std::vector<double>> times(names.size());
  std::vector<double> graph_forward;  // upload + replay of the recorded forward
  size_t points = 0;
  for (int r = 0; r < a.repeat + 1; ++r) {  // the first run plans memory and warms up
    std::vector<double> t(names.size(), 0.0);
    const auto start = std::chrono::steady_clock::now();
    auto t0 = start;
    const Scan scan = read_scan(scan_path);
    points = scan.points.size();
    t[0] = ms_since(t0);
    t0 = std::chrono::steady_clock::now();
    ModelConfig pillars_only = model;
    pillars_only.occupancy = OccupancyInput::None;
    pillars_only.grid_map_input = false;
    ScanInputs inputs = compute_scan_inputs(scan.points, Eigen::Vector3d::Zero(), pillars_only,
                                            host::SampleMode::Inference, nullptr);
    t[1] = ms_since(t0);
    t0 = std::chrono::steady_clock::now();
    if (model.occupancy != OccupancyInput::None || model.grid_map_input) {
      ScanInputs maps = compute_scan_inputs(scan.points, Eigen::Vector3d::Zero(),
                                            [&] {
                                              ModelConfig m = model;
                                              m.pillar_input = false;
                                              m.pillar_channels = 1;
                                              return m;
                                            }(),
                                            host::SampleMode::Inference, nullptr);
      inputs.occupancy = std::move(maps.occupancy);
      inputs.grid_map = std::move(maps.grid_map);
    }
    t[2] = ms_since(t0);
    const ModelBatch batch = collate(std::move(inputs), model);
    net.forward(batch, false);
    const auto& st = net.stage_times();
    t[3] = st.upload, t[4] = st.pfn, t[5] = st.scatter, t[6] = st.occupancy, t[7] = st.unet, t[8] = st.head;
    t0 = std::chrono::steady_clock::now();
    Tensor<uint8_t> labels = net.predict_labels();
    labels.reshape({model.grid.height(), model.grid.width()});
    write_label_map(scratch / "prediction.u8", labels, classes);
    write_label_map(scratch / "prediction.png", labels, classes);
    t[9] = ms_since(t0);
    t[10] = ms_since(start);
    if (r > 0)
      for (size_t i = 0; i < names.size(); ++i) times[i].push_back(t[i]);
    if (backend->supports_capture()) {  // the first run records the graph
      net.set_stage_timing(false);
      const double before = backend->clock_ms();
      net.forward(batch, false);
      const double replay_ms = backend->clock_ms() - before;
      net.set_stage_timing(true);
      if (r > 0) graph_forward.push_back(replay_ms);
    }
  }
  std::error_code ec;
  fs::remove_all(scratch, ec);
  fmt::print("pillarseg bench: device {}, {} threads, grid {} x {}, C {}, b {}, {} upsampling, occupancy {}\n",
             backend->name(), num_threads(), model.grid.width(), model.grid.height(), model.pillar_channels,
             model.base_width, model.transposed ? "transposed" : "bilinear", occupancy_name(model.occupancy));
  fmt::print("scan: {} ({} points); median of {} runs after one warm-up\n", scan_path.string(), points, a.repeat);
  fmt::print("{:<14} {:>10}\n", "stage", "ms");
  for (size_t i = 0; i < names.size(); ++i)
    if (listed(i)) fmt::print("{:<14} {:>10.2f}\n", names[i], median(times[i]));
  fmt::print("throughput: {:.2f} scans/s, {:.2f} M points/s\n", 1000.0 / median(times.back()),
             static_cast<double>(points) / median(times.back()) / 1000.0);
  if (!graph_forward.empty()) {
    double staged = 0;
    for (size_t i = 3; i <= 8; ++i) staged += median(times[i]);
    fmt::print("forward as a graph replay (upload included): {:.2f} ms; stage by stage above: {:.2f} ms ({:.2f}x)\n",
               median(graph_forward), staged, staged / std::max(median(graph_forward), 1e-9));
  }
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  fmt::print("peak resident memory: {:.0f} MiB (host; activations planned: {:.0f} MiB)\n",
             static_cast<double>(usage.ru_maxrss) / 1024.0, static_cast<double>(net.activation_bytes()) / (1 << 20));
}

}  // namespace

void add_bench(CLI::App& app) {
  auto a = std::make_shared<BenchArgs>();
  CLI::App* cmd = app.add_subcommand("bench", "Stage timings of one inference (default: the paper's full-size model "
                                              "on a simulated 120k-point scan)");
  cmd->add_option("--device", a->device, "cpu or cuda")->check(CLI::IsMember({"cpu", "cuda"}));
  cmd->add_option("--conv", a->conv, "Conv2d with --device cuda: own (our kernels), cudnn or cublas (for comparison)")->check(CLI::IsMember({"own", "cudnn", "cublas"}));
  cmd->add_option("--config", a->config, "run config YAML (default: the paper's settings)");
  cmd->add_flag("--transposed", a->transposed, "use the transposed-convolution U-Net");
  cmd->add_option("--weights", a->weights, "checkpoint (default: random weights; timings do not depend on them)");
  cmd->add_option("--scan", a->scan, "scan file (.bin); default: a simulated scan");
  cmd->add_option("--repeat", a->repeat, "timed repetitions")->check(CLI::PositiveNumber);
  cmd->callback([a] { run_bench(*a); });
}

}  // namespace pillarseg::cli
