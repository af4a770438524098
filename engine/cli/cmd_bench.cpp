// pillarseg bench: the stage breakdown of one inference on a real-size scan through the whole
// pipeline on the chosen device (engine/pipeline/segmenter.hpp): read, upload (the raw points),
// pillars (gather, decoration, cells), input maps (ray walks, occupancy or grid-map layers), PFN,
// scatter, occupancy stream, U-Net, head, predict (arg-max, masking), download (the label map),
// write; median over repetitions, the total, and the process's peak resident memory. Stages the
// config does not have are not listed. Device stages are timed on the backend's clock (CUDA events
// on a CUDA backend), which waits between stages; where the backend records graphs, the whole
// pipeline is also timed as the steady state runs it (upload, one graph replay a copy of the scan,
// download). On a CUDA backend the bytes that cross the bus per scan are counted, and compared
// with inputs prepared on the host and uploaded (the network's decorated pillars and maps). --ops
// adds the network op by op (print_op_table), --roofline each op's and a training step's lower
// bound on a GPU (engine/model/roofline.hpp). --save-canvas writes the U-Net's FP32 input canvas
// of the scan as .npy, for calibrating a peer's INT8 quantization on real inputs (bench/peer/).
#include <fmt/format.h>
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <optional>

#include "core/io.hpp"
#include "core/parallel.hpp"
#include "engine/cli/cli_util.hpp"
#include "engine/cli/commands.hpp"
#include "engine/cpu/bf16_conv.hpp"
#include "engine/cpu/int8_conv.hpp"
#include "engine/data/point_formats.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/model/calibration.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/model/op_record.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "engine/model/roofline.hpp"
#include "engine/pipeline/scan_inputs.hpp"
#include "engine/pipeline/segmenter.hpp"
#include "engine/render/label_map.hpp"
#include "engine/sim/simulate.hpp"
#include "host/batchnorm.hpp"
#include "host/conv2d.hpp"
#include "host/pfn.hpp"
#include "host/scatter.hpp"

namespace pillarseg::cli {

namespace {

struct BenchArgs {
  std::string config, weights, scan, format = "auto";
  DeviceArgs device;
  int repeat = 5;
  int flips = 1;
  bool transposed = false, mask_unobserved = false;
  bool ops = false;      // the network's time per op of its graph
  std::string roofline;  // a GPU (engine/model/roofline.hpp) to bound each op's time on
  std::string save_canvas;  // a .npy file for the U-Net's FP32 input canvas of the scan
};

double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

// Bytes over the bus for one scan whose inputs are prepared on the host (compute_scan_inputs)
// and uploaded, and whose labels come back: what --device cuda did before the device pipeline.
// The CPU's model name (/proc/cpuinfo), "unknown" where it is not there: figures say which CPU
// ran them.
std::string cpu_model_name() {
  std::ifstream in("/proc/cpuinfo");
  for (std::string line; std::getline(in, line);) {
    if (line.rfind("model name", 0) != 0) continue;
    const size_t colon = line.find(':');
    if (colon == std::string::npos) break;
    const size_t start = line.find_first_not_of(" \t", colon + 1);
    return start == std::string::npos ? "unknown" : line.substr(start);
  }
  return "unknown";
}

// The evaluation graph's convolutions by arithmetic, "11 convolutions BF16, 6 FP32 where that is
// faster on this CPU": in a BF16 network on the CPU, a convolution whose FP32 kernel is the faster
// there runs FP32 (Backend::prepared_conv_dtype).
std::string conv_arithmetic(const Graph& g) {
  int half = 0, fp32 = 0;
  for (const GraphNode& n : g.nodes()) {
    if (n.op != OpKind::PreparedConv2d && n.op != OpKind::PreparedConvTranspose2d) continue;
    ++(g.at(n.as<PreparedConv2dArgs>().prepared).dtype == DType::F32 ? fp32 : half);
  }
  const auto convolutions = [](int n) { return fmt::format("{} convolution{}", n, n == 1 ? "" : "s"); };
  if (fp32 == 0) return convolutions(half) + " BF16";
  return fmt::format("{} BF16, {} FP32 where that is faster on this CPU", convolutions(half), fp32);
}

// The INT8 evaluation graph's U-Net convolutions by form on this CPU, "10 convolutions in the
// Winograd domain F(2x2, 3x3), 7 direct", by the backend's own rule (cpu::int8_forward_in_winograd).
std::string int8_conv_forms(const Graph& g) {
  int winograd = 0, direct = 0;
  const cpu::Int8Kernels kernels = cpu::native_int8_kernels();
  const cpu::Int8WinogradRule rule = cpu::int8_winograd_rule();
  for (const GraphNode& n : g.nodes()) {
    if (n.op != OpKind::PreparedConv2d && n.op != OpKind::PreparedConvTranspose2d) continue;
    if (g.at(n.as<PreparedConv2dArgs>().prepared).dtype != DType::I8) continue;
    const bool in_winograd = cpu::int8_forward_in_winograd(kernels, n.weight, n.pad, n.op != OpKind::PreparedConv2d,
                                                           n.int8_input.has_winograd(), rule);
    ++(in_winograd ? winograd : direct);
  }
  const auto convolutions = [](int n) { return fmt::format("{} convolution{}", n, n == 1 ? "" : "s"); };
  if (winograd == 0) return convolutions(direct) + " direct";
  return fmt::format("{} in the Winograd domain F(2x2, 3x3), {} direct", convolutions(winograd), direct);
}

int64_t host_inputs_bytes(ScanSegmenter& segmenter, const Scan& scan) {
  Backend& backend = segmenter.backend();
  const ModelConfig& model = segmenter.model();
  const Backend::Counters before = backend.counters();
  ScanInputs inputs = compute_scan_inputs(scan.points, Eigen::Vector3d::Zero(), model, host::SampleMode::Inference,
                                          nullptr);
  segmenter.net().forward(collate(std::move(inputs), model), false);
  segmenter.net().predict_labels();
  const Backend::Counters after = backend.counters();
  return (after.bytes_uploaded - before.bytes_uploaded) + (after.bytes_downloaded - before.bytes_downloaded);
}

// Which cells of the model's grid hold a point of the scan (H W, row-major).
std::vector<bool> cells_with_points(const ModelConfig& model, const Scan& scan) {
  std::vector<bool> with_points(static_cast<size_t>(model.grid.cells()), false);
  for (const Point& p : scan.points)
    if (model.grid.contains(p.x, p.y, p.z))
      with_points[static_cast<size_t>(model.grid.cell_index(p.x, p.y))] = true;
  return with_points;
}

// The roofline bound of a training step (engine/model/roofline.hpp) for this config at batch 2
// with twice this scan's pillars, in the bench's precision (the convolutions on the tensor cores,
// the rest FP32, as the CUDA backend trains), plus the AdamW step (7 floats a parameter moved),
// and what it makes of the paper's training: a model of the same config planned for training (no
// step runs) on this backend, or on the emulated CUDA backend where this one trains in FP32 only.
void print_training_bound(ScanSegmenter& segmenter, const Scan& scan, const GpuPeaks& gpu) {
  const ModelConfig& model = segmenter.model();
  const std::vector<bool> with_points = cells_with_points(model, scan);
  int64_t pillars = std::count(with_points.begin(), with_points.end(), true);
  if (model.max_pillars > 0) pillars = std::min<int64_t>(pillars, model.max_pillars);
  // A backend that trains in the bench's precision: this one, or else (a CPU) the emulated CUDA
  // backend where this program has it, only to plan the graph.
  const Precision precision = segmenter.net().precision();
  Backend* backend = &segmenter.backend();
  std::unique_ptr<Backend> planner;
  if (precision != Precision::F32 && !backend->supports_training_precision(precision) &&
      available_devices().find("emu") != std::string::npos) {
    planner = make_backend("emu");
    backend = planner.get();
  }
  std::string why;
  const bool trains_half =
      precision != Precision::F32 && backend->supports_training_precision(precision, &why);
  PillarSegNet net(model, *backend);
  if (trains_half) net.set_training_precision(precision);
  const int batch = 2;
  net.prepare(batch, batch * pillars, /*training=*/true);
  const GraphBound step = graph_bound(net.graph(true), batch * pillars, gpu);
  const double adam_ms = 7.0 * 4.0 * static_cast<double>(net.parameters().values().numel()) /
                         (gpu.tb_per_s * 1e12) * 1e3;
  constexpr double kPaperSteps = 19130.0 * 30 / 2;  // the paper's scans x epochs, batch 2
  fmt::print(
      "training step on {} (batch {}, {} pillar rows, {} convolutions{}): bound {:.3f} ms ({:.3f} "
      "compute, {:.3f} memory) + AdamW {:.3f} ms; the paper's {:.0f} steps (19,130 scans x 30 "
      "epochs): at least {:.2f} h on one, the data loading aside\n",
      gpu.name, batch, batch * pillars, precision_name(trains_half ? precision : Precision::F32),
      precision == Precision::F32 || trains_half ? "" : ", " + why, step.ms(), step.compute_ms,
      step.memory_ms, adam_ms, kPaperSteps, kPaperSteps * (step.ms() + adam_ms) / 3.6e6);
}

// The network's time per op of its evaluation graph (PillarSegNet::set_op_timing: the device
// waits after every node, no graph replay), mean per run over `repeat` runs, with each op's FLOPs
// and least bytes, what the emulation counted its tensor cores issue, and, given a GPU, the
// roofline bound of each op there (engine/model/roofline.hpp).
void print_op_table(ScanSegmenter& segmenter, const Scan& scan, Tensor<uint8_t>& labels, int repeat,
                    const std::optional<GpuPeaks>& roofline) {
  PillarSegNet& net = segmenter.net();
  net.clear_op_times();
  net.set_op_timing(true);
  segmenter.set_stage_timing(true);  // runs the pipeline op by op, not as a recorded graph
  for (int r = 0; r < repeat; ++r) segmenter.segment(scan.points, labels.data());
  segmenter.set_stage_timing(false);
  net.set_op_timing(false);
  std::vector<std::pair<std::string, PillarSegNet::OpTime>> ops(net.op_times().begin(),
                                                                net.op_times().end());
  net.clear_op_times();
  std::sort(ops.begin(), ops.end(),
            [](const auto& x, const auto& y) { return x.second.ms > y.second.ms; });
  const bool counted = std::any_of(ops.begin(), ops.end(),
                                   [](const auto& o) { return o.second.tensor_core_flops >= 0; });
  const bool bounded = roofline.has_value();
  const GpuPeaks gpu = roofline.value_or(GpuPeaks{});
  fmt::print(
      "the network per op of its graph, mean of {} runs ({}, waiting for the device after every "
      "op):\n",
      repeat, segmenter.backend().name());
  std::string header = fmt::format("{:<36} {:>6} {:>9} {:>9} {:>9} {:>9}", "op", "calls", "ms",
                                   "GFLOP", "MB", "GFLOP/s");
  if (counted) header += fmt::format(" {:>10} {:>7} {:>9}", "TC GFLOP", "useful", "async MB");
  if (bounded) header += fmt::format(" {:>10} {:>7}", fmt::format("{} ms", gpu.name), "bound");
  fmt::print("{}\n", header);
  const double runs = repeat;
  PillarSegNet::OpTime total;
  double compute_bound_ms = 0, memory_bound_ms = 0;  // the bounds of compute- and memory-bound ops
  double tensor_core_flops = 0, async_bytes = 0;
  for (const auto& [name, t] : ops) {
    const double ms = t.ms / runs, flops = t.flops / runs, bytes = t.bytes / runs;
    std::string line =
        fmt::format("{:<36} {:>6} {:>9.3f} {:>9.3f} {:>9.2f} {:>9.1f}", name, t.calls / repeat, ms,
                    flops * 1e-9, bytes * 1e-6, ms > 0 ? flops / (ms * 1e-3) * 1e-9 : 0.0);
    if (counted) {
      if (t.tensor_core_flops > 0) {
        line +=
            fmt::format(" {:>10.3f} {:>6.1f}% {:>9.2f}", t.tensor_core_flops / runs * 1e-9,
                        100.0 * t.flops / t.tensor_core_flops, t.async_copy_bytes / runs * 1e-6);
        tensor_core_flops += t.tensor_core_flops / runs;
        async_bytes += t.async_copy_bytes / runs;
      } else {
        line += fmt::format(" {:>10} {:>7} {:>9}", "-", "-", "-");
      }
    }
    if (bounded) {
      const RooflineBound b = roofline_bound(flops, bytes, t.matrix_units, gpu, t.int8_units);
      (b.memory_bound() ? memory_bound_ms : compute_bound_ms) += b.ms();
      line += fmt::format(" {:>10.4f} {:>7}", b.ms(), b.memory_bound() ? "memory" : "compute");
    }
    fmt::print("{}\n", line);
    total.ms += ms, total.flops += flops, total.bytes += bytes;
  }
  fmt::print("{:<36} {:>6} {:>9.3f} {:>9.3f} {:>9.2f} {:>9.1f}\n", "total", "", total.ms,
             total.flops * 1e-9, total.bytes * 1e-6,
             total.ms > 0 ? total.flops / (total.ms * 1e-3) * 1e-9 : 0.0);
  if (counted && tensor_core_flops > 0) {
    fmt::print(
        "tensor cores (counted by the emulation): {:.3f} GFLOP issued a run, {:.2f} MB copied by "
        "cp.async\n",
        tensor_core_flops * 1e-9, async_bytes * 1e-6);
  }
  if (bounded) {
    fmt::print(
        "roofline bound on {} ({} TFLOP/s FP32, {} TFLOP/s dense 16-bit tensor cores, {} TOP/s INT8, {} TB/s; "
        "{}): {:.3f} ms for the network, PFN to head ({:.3f} ms in compute-bound ops, {:.3f} ms "
        "in memory-bound ones) - a lower bound, not a prediction: no kernel runs at a peak, and "
        "the pillar gather, decoration, input maps and predictions are outside the graph\n",
        gpu.name, gpu.fp32_tflops, gpu.half_tflops, gpu.int8_tops, gpu.tb_per_s, gpu.source,
        compute_bound_ms + memory_bound_ms, compute_bound_ms, memory_bound_ms);
    print_training_bound(segmenter, scan, gpu);
  }
}

// The U-Net's FP32 input canvas (1, I, H, W) of the scan, from the CPU reference (host/) with the
// network's parameters in evaluation: the PFN and scatter, the occupancy stream and the grid-map
// layers in the canvas's channel order (engine/model/model_graph.cpp), whatever precision the
// bench runs. Written as NumPy .npy (version 1.0, '<f4', C order): what a peer calibrates its INT8
// quantization on (bench/peer/openvino_peer.py).
void save_canvas(ScanSegmenter& segmenter, const Scan& scan, const std::filesystem::path& path) {
  const ModelConfig& model = segmenter.model();
  const ParameterSet& params = segmenter.net().parameters();
  const auto param = [&](const std::string& name) {
    const int index = params.find(name);
    PS_CHECK(index >= 0, "--save-canvas: the model has no parameter '{}'", name);
    return params.download(index);
  };
  const int64_t height = model.grid.height(), width = model.grid.width(), plane = height * width;
  ScanInputs inputs = compute_scan_inputs(scan.points, Eigen::Vector3d::Zero(), model,
                                          host::SampleMode::Inference, nullptr);
  Tensor<float> canvas = Tensor<float>::zeros({1, model.input_channels(), height, width});
  int64_t channel = 0;
  const auto append = [&](const Tensor<float>& stream) {  // (1, c, H, W) after `channel`
    PS_CHECK(stream.numel() % plane == 0 && channel + stream.numel() / plane <= canvas.dim(1),
             "--save-canvas: a stream of shape {} does not fit the canvas {}", shape_str(stream.shape()),
             shape_str(canvas.shape()));
    std::copy(stream.begin(), stream.end(), canvas.data() + channel * plane);
    channel += stream.numel() / plane;
  };
  if (model.pillar_input) {
    const std::string pfn = "vfe.pfn_layers.0.";
    Tensor<float> features;
    host::pfn_forward_eval(inputs.pillar_points, param(pfn + "linear.weight"), param(pfn + "norm.weight"),
                           param(pfn + "norm.bias"), param(pfn + "norm.running_mean"),
                           param(pfn + "norm.running_var"), host::kPfnNormOptions, features);
    Tensor<int32_t> cells({inputs.pillar_cells.dim(0), 3});
    host::batch_cells(inputs.pillar_cells, 0, cells);
    Tensor<float> scattered;
    host::scatter_forward(features, cells, 1, height, width, scattered);
    append(scattered);
  }
  if (model.occupancy != OccupancyInput::None) {
    Tensor<float> occupancy = std::move(inputs.occupancy);
    occupancy.reshape({1, occupancy.dim(0), height, width});
    Tensor<float> conv, stream;
    host::conv2d_forward(occupancy, param("occupancy.conv.weight"), nullptr, 1, conv);
    // The occupancy stream's BatchNorm has the PFN's eps and momentum (DESIGN.md section 2).
    host::batchnorm_relu_forward_eval(conv, param("occupancy.norm.weight"), param("occupancy.norm.bias"),
                                      param("occupancy.norm.running_mean"), param("occupancy.norm.running_var"),
                                      host::kPfnNormOptions, stream);
    append(stream);
  }
  if (model.grid_map_input) append(inputs.grid_map);
  PS_CHECK(channel == canvas.dim(1), "--save-canvas: the streams fill {} of the canvas's {} channels", channel,
           canvas.dim(1));
  std::string header = fmt::format("{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, {}, {}, {}), }}",
                                    canvas.dim(0), canvas.dim(1), canvas.dim(2), canvas.dim(3));
  header.append(63 - (10 + header.size()) % 64, ' ');  // the data starts on a 64-byte boundary
  header += '\n';
  write_file_atomic(path, [&](std::ostream& out) {
    const uint16_t header_size = static_cast<uint16_t>(header.size());  // little-endian, as x86 and ARM
    out.write("\x93NUMPY\x01\x00", 8);
    out.write(reinterpret_cast<const char*>(&header_size), 2);
    out.write(header.data(), static_cast<std::streamsize>(header.size()));
    out.write(reinterpret_cast<const char*>(canvas.data()), static_cast<std::streamsize>(canvas.numel() * 4));
  });
}

void run_bench(const BenchArgs& a) {
  namespace fs = std::filesystem;
  std::optional<GpuPeaks> roofline;  // checked before anything runs
  if (!a.roofline.empty()) roofline = parse_gpu(a.roofline);
  ModelConfig model;
  if (!a.weights.empty() && a.config.empty()) model = config_for(read_checkpoint(a.weights), "").model;
  if (!a.config.empty()) model = load_run_config(a.config).model;
  model.transposed = model.transposed || a.transposed;
  SegmenterOptions options = segmenter_options(a.device);
  options.mask_unobserved = a.mask_unobserved;
  options.flips = a.flips;
  PS_CHECK(a.flips == 1 || (!a.ops && a.roofline.empty()),
           "--flips {}: --ops and --roofline time one pass of the network; leave out --flips", a.flips);
  // The device first: no device, no scratch files left behind.
  ScanSegmenter segmenter(model, make_backend(options.device, options.backend), options);
  Backend& backend = segmenter.backend();
  const fs::path scratch = fs::temp_directory_path() / fmt::format("pillarseg_bench_{}", ::getpid());
  fs::path scan_path = a.scan;
  PointFormat format = parse_point_format(a.format);
  if (scan_path.empty()) {
    // A simulated real-size scan (about 120k points).
    sim::SequenceSimulator simulator(sim::sequence_seed(1, 0), 1);
    scan_path = scratch / "scan.bin";
    write_bin(scan_path, simulator.scan(0).points);
    format = PointFormat::Kitti;
  }
  if (!a.weights.empty()) load_weights(read_checkpoint(a.weights), segmenter.net(), false);
  PillarSegNet& net = segmenter.net();
  if (net.precision() == Precision::I8 && net.int8_inputs().empty()) {
    // No calibrated scales: the benched scan's own FP32 forward gives them (engine/model/calibration.hpp).
    InputScaleCalibrator calibrator;
    net.set_precision(Precision::F32);
    {
      const CalibrationScope observing(net, calibrator);
      Tensor<uint8_t> scratch_labels({model.grid.height(), model.grid.width()});
      segmenter.segment(read_points(scan_path, format).points, scratch_labels.data());
    }
    net.set_int8_inputs(calibrator.inputs());
    net.set_precision(Precision::I8);
    fmt::print("--precision int8: no INT8 scales in {}; calibrated on the benched scan itself ({}th "
               "percentile; pillarseg calibrate gives a checkpoint its own)\n",
               a.weights.empty() ? "the random weights" : a.weights, calibrator.percentile());
  }
  const ClassTable classes = ClassTable::defaults();

  const std::vector<std::string> names = {"read",   "upload", "pillars", "input maps", "PFN",   "scatter", "occupancy",
                                          "U-Net",  "head",   "predict", "download",   "write", "total"};
  const bool has_maps = model.occupancy != OccupancyInput::None || model.grid_map_input || a.mask_unobserved;
  const auto listed = [&](const std::string& name) {
    if (name == "pillars" || name == "PFN" || name == "scatter") return model.pillar_input;
    if (name == "input maps") return has_maps;
    if (name == "occupancy") return model.occupancy != OccupancyInput::None;
    return true;
  };
  std::vector<std::vector<double>> times(names.size());
  std::vector<double> steady;  // upload + graph replay + download
  int64_t steady_bytes = 0;
  Tensor<uint8_t> labels({model.grid.height(), model.grid.width()});
  size_t points = 0;
  for (int r = 0; r < a.repeat + 1; ++r) {  // the first run plans memory and warms up
    std::vector<double> t(names.size(), 0.0);
    const auto start = std::chrono::steady_clock::now();
    const Scan scan = read_points(scan_path, format);
    points = scan.points.size();
    t[0] = ms_since(start);
    segmenter.set_stage_timing(true);
    segmenter.segment(scan.points, labels.data());
    segmenter.set_stage_timing(false);
    const ScanSegmenter::StageTimes& st = segmenter.stage_times();
    const double stages[] = {st.upload, st.pillars, st.maps,    st.pfn,     st.scatter,
                             st.occupancy, st.unet, st.head, st.predict, st.download};
    std::copy(std::begin(stages), std::end(stages), t.begin() + 1);
    const auto t0 = std::chrono::steady_clock::now();
    write_label_map(scratch / "prediction.u8", labels, classes);
    write_label_map(scratch / "prediction.png", labels, classes);
    t[11] = ms_since(t0);
    t[12] = ms_since(start);
    if (r > 0)
      for (size_t i = 0; i < names.size(); ++i) times[i].push_back(t[i]);
    if (backend.supports_capture()) {  // the first run records the graph
      const Backend::Counters before = backend.counters();
      const double begin = backend.clock_ms();
      segmenter.segment(scan.points, labels.data());
      const double replay_ms = backend.clock_ms() - begin;
      const Backend::Counters after = backend.counters();
      steady_bytes = (after.bytes_uploaded - before.bytes_uploaded) + (after.bytes_downloaded - before.bytes_downloaded);
      if (r > 0) steady.push_back(replay_ms);
    }
  }
  const Scan scan = read_points(scan_path, format);  // for the checks below, before the scratch folder goes
  if (!a.save_canvas.empty()) save_canvas(segmenter, scan, a.save_canvas);
  std::error_code ec;
  fs::remove_all(scratch, ec);
  int64_t host_bytes = 0;
  if (backend.device() != Device::Cpu) host_bytes = host_inputs_bytes(segmenter, scan);
  // Which BF16 kernels the CPU runs (the AMX tiles or AVX512_BF16 alone), as the figures depend on it.
  std::string precision_label = precision_name(segmenter.net().precision());
  if (backend.device() == Device::Cpu && segmenter.net().precision() == Precision::BF16)
    precision_label += fmt::format(" ({}: {})", cpu::bf16_kernels_name(cpu::native_bf16_kernels()),
                                   conv_arithmetic(segmenter.net().graph(false)));
  if (backend.device() == Device::Cpu && segmenter.net().precision() == Precision::I8)
    precision_label += fmt::format(" ({}: {})", cpu::int8_kernels_name(cpu::native_int8_kernels()),
                                   int8_conv_forms(segmenter.net().graph(false)));
  fmt::print("pillarseg bench: device {}, precision {}, {} threads, grid {} x {}, C {}, b {}, {} upsampling, "
             "occupancy {}{}{}\n",
             backend.name(), precision_label, num_threads(), model.grid.width(), model.grid.height(), model.pillar_channels,
             model.base_width, model.transposed ? "transposed" : "bilinear", occupancy_name(model.occupancy),
             model.grid_map_input ? ", grid-map input" : "",
             a.flips > 1 ? fmt::format(", {} flips (each stage the sum over the {} passes)", a.flips, a.flips) : "");
  std::string bf16_line, why;
  if (!cpu::avx512_bf16_available(&why)) {
    bf16_line = "no BF16 kernels (" + why + ")";
  } else if (!cpu::amx_bf16_available(&why)) {
    bf16_line = "BF16 on avx512_bf16 (no AMX: " + why + ")";
  } else {
    bf16_line = fmt::format("BF16 on {}", cpu::bf16_kernels_name(cpu::native_bf16_kernels()));
  }
  fmt::print("host cpu: {}, {} threads; {}\n", cpu_model_name(), num_threads(), bf16_line);
  fmt::print("scan: {} ({} points); median of {} runs after one warm-up, each stage timed on the backend's "
             "clock\n",
             scan_path.string(), points, a.repeat);
  fmt::print("{:<14} {:>10}\n", "stage", "ms");
  for (size_t i = 0; i < names.size(); ++i)
    if (listed(names[i])) fmt::print("{:<14} {:>10.2f}\n", names[i], median(times[i]));
  fmt::print("throughput: {:.2f} scans/s, {:.2f} M points/s\n", 1000.0 / median(times.back()),
             static_cast<double>(points) / median(times.back()) / 1000.0);
  if (!steady.empty()) {
    double staged = 0;
    for (size_t i = 1; i <= 10; ++i) staged += median(times[i]);
    const std::string replays =
        a.flips > 1 ? fmt::format("{} graph replays, one per copy", a.flips) : std::string("one graph replay");
    fmt::print("steady state (upload, {}, download): {:.2f} ms; stage by stage above: {:.2f} ms ({:.2f}x)\n",
               replays, median(steady), staged, staged / std::max(median(steady), 1e-9));
  }
  if (backend.device() != Device::Cpu) {
    fmt::print("bytes over the bus per scan: {:.2f} MB (the raw points up, the label map down); with the inputs "
               "prepared on the host and uploaded: {:.2f} MB ({:.1f}x)\n",
               static_cast<double>(steady_bytes) / 1e6, static_cast<double>(host_bytes) / 1e6,
               static_cast<double>(host_bytes) / std::max<double>(static_cast<double>(steady_bytes), 1.0));
  }
  if (a.ops || !a.roofline.empty()) print_op_table(segmenter, scan, labels, a.repeat, roofline);
  if (segmenter.net().precision() != Precision::F32) {
    // The same network in FP32 on another backend of the same kind, on the same scan: how far
    // the 16-bit convolutions move the result.
    SegmenterOptions fp32_options = options;
    fp32_options.precision = Precision::F32;
    ScanSegmenter reference(model, make_backend(options.device, options.backend), fp32_options);
    if (!a.weights.empty()) load_weights(read_checkpoint(a.weights), reference.net(), false);
    const int64_t cells = model.grid.cells();
    Tensor<uint8_t> half_labels({model.grid.height(), model.grid.width()}), fp32_labels(half_labels.shape());
    Tensor<float> half_probs({12, model.grid.height(), model.grid.width()}), fp32_probs(half_probs.shape());
    segmenter.segment(scan.points, half_labels.data(), half_probs.data());
    reference.segment(scan.points, fp32_labels.data(), fp32_probs.data());
    const std::vector<bool> with_points = cells_with_points(model, scan);
    int64_t occupied = 0, agree = 0;
    for (int64_t c = 0; c < cells; ++c) {
      if (!with_points[static_cast<size_t>(c)]) continue;
      ++occupied;
      agree += half_labels.data()[c] == fp32_labels.data()[c];
    }
    double largest = 0;
    for (int64_t i = 0; i < half_probs.numel(); ++i)
      largest = std::max(largest, static_cast<double>(std::abs(half_probs.data()[i] - fp32_probs.data()[i])));
    fmt::print("{} against fp32: arg-max agreement {:.3f}% of the {} cells with points, largest probability "
               "difference {:.4f}\n",
               precision_name(segmenter.net().precision()), 100.0 * static_cast<double>(agree) /
                                                                std::max<double>(static_cast<double>(occupied), 1.0),
               occupied, largest);
  }
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  fmt::print("peak resident memory: {:.0f} MiB (host; activations planned: {:.0f} MiB)\n",
             static_cast<double>(usage.ru_maxrss) / 1024.0,
             static_cast<double>(segmenter.net().activation_bytes()) / (1 << 20));
}

}  // namespace

void add_bench(CLI::App& app) {
  auto a = std::make_shared<BenchArgs>();
  CLI::App* cmd = app.add_subcommand("bench", "Stage timings of one inference, raw points to label map (default: the "
                                              "paper's full-size model on a simulated 120k-point scan)");
  add_device_options(cmd, a->device);
  cmd->add_option("--config", a->config, "run config YAML (default: the paper's settings, or the checkpoint's)");
  cmd->add_flag("--transposed", a->transposed, "use the transposed-convolution U-Net");
  cmd->add_flag("--mask-unobserved", a->mask_unobserved, "mask cells no ray observed (ray walks for every model)");
  cmd->add_option("--weights", a->weights, "checkpoint (default: random weights; timings do not depend on them)");
  cmd->add_option("--scan", a->scan,
                  "point file (.bin KITTI, .pcd, .ply, .npy, .pcd.bin nuScenes: docs/formats.md); default: a "
                  "simulated scan");
  cmd->add_option("--format", a->format, "the point file's format: auto (by extension), kitti, pcd, ply, npy, nuscenes")
      ->check(CLI::IsMember({"auto", "kitti", "pcd", "ply", "npy", "nuscenes"}));
  cmd->add_option("--repeat", a->repeat, "timed repetitions")->check(CLI::PositiveNumber);
  add_flips_option(cmd, a->flips);
  cmd->add_flag(
      "--ops", a->ops,
      "also time the network per op of its graph, with each op's FLOPs and least bytes (and, on "
      "--device emu, what its tensor cores issued)");
  cmd->add_option(
      "--roofline", a->roofline,
      "implies --ops: each op's roofline bound on this GPU (h200, h100-sxm, h100-pcie, a100-sxm, "
      "l4, "
      "rtx4090, orin-agx-64, or custom:FP32_TFLOPS:HALF_TFLOPS:TB_PER_S), and a training step's "
      "(its graph planned, not run: the plan's memory is allocated)");
  cmd->add_option("--save-canvas", a->save_canvas,
                  "write the U-Net's FP32 input canvas of the scan, (1, I, H, W), to this .npy file (float32, C "
                  "order), e.g. to calibrate a peer's INT8 quantization");
  cmd->callback([a] { run_bench(*a); });
}

}  // namespace pillarseg::cli
