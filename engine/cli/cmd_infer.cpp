// pillarseg infer / render: scans through a trained model (label map PNG, class ids,
// probabilities), and the paper's Fig. 3 panels (points, observability, prediction, ground
// truth) for a scan of a sequence, laid out by engine/render/figure.hpp. Both run the whole
// pipeline on the chosen device (engine/pipeline/segmenter.hpp). Over several scans, infer reads
// the next scan and writes the last result while the current one runs.
#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <future>
#include <optional>
#include <vector>

#include "core/io.hpp"
#include "engine/cli/cli_util.hpp"
#include "engine/cli/commands.hpp"
#include "engine/data/ground_truth.hpp"
#include "engine/data/input_mapping.hpp"
#include "engine/data/point_formats.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/pipeline/segmenter.hpp"
#include "engine/render/figure.hpp"
#include "engine/render/label_map.hpp"
#include "engine/render/render.hpp"
#include "engine/util/progress.hpp"
#include "host/raywalk.hpp"
#include "weights_io/half.hpp"

namespace pillarseg::cli {

namespace {

namespace fs = std::filesystem;

struct InferArgs {
  std::string weights, out, config, format = "auto";
  std::vector<std::string> scans;
  DeviceArgs device;
  bool probabilities = false, mask_unobserved = false, no_png = false;
  int flips = 1;
  // The input mapping's parts set on the command line (the run config's input: section otherwise).
  std::optional<float> reflectance_scale, reflectance_offset;
  bool no_reflectance = false;
  std::vector<double> transform;
  std::optional<double> height, roll, pitch, yaw;
};

struct RenderArgs {
  std::string data, weights, config, out, mode = "sparse", cache;
  DeviceArgs device;
  int sequence = -1, scan = -1;
  bool mask_unobserved = false;
  int flips = 1;
};

std::unique_ptr<ScanSegmenter> open_for(const std::string& weights, const std::string& config,
                                        const DeviceArgs& device, bool mask_unobserved, int flips) {
  SegmenterOptions options = segmenter_options(device);
  options.mask_unobserved = mask_unobserved;
  options.flips = flips;
  return open_segmenter(weights, config, options);
}

// The input mapping of the run config with the parts the command line sets replaced.
InputMapping input_mapping(const InferArgs& a, const InputMapping& from_config) {
  InputMapping m = from_config;
  const bool scaled = a.reflectance_scale || a.reflectance_offset;
  PS_CHECK(!(a.no_reflectance && scaled), "--no-reflectance: cannot also scale the reflectance (--reflectance-scale, "
                                          "--reflectance-offset)");
  if (a.no_reflectance) m.reflectance = {ReflectanceMapping::Kind::None, 1, 0, true};
  if (scaled)
    m.reflectance = {ReflectanceMapping::Kind::Scale, a.reflectance_scale.value_or(1.0f),
                     a.reflectance_offset.value_or(0.0f), true};
  const bool angles = a.height || a.roll || a.pitch || a.yaw;
  PS_CHECK(a.transform.empty() || !angles, "--transform: give either the 16 numbers or --height, --roll, --pitch, "
                                           "--yaw, not both");
  if (!a.transform.empty()) m.transform = transform_from_numbers(a.transform, "--transform");
  if (angles)
    m.transform = transform_from_angles(a.height.value_or(0), a.roll.value_or(0), a.pitch.value_or(0),
                                        a.yaw.value_or(0));
  return m;
}

// The point files named on the command line: files as given, directories by their files with a
// point-file extension (or, for a SemanticKITTI sequence directory, its velodyne/'s), sorted.
std::vector<fs::path> scan_files(const std::vector<std::string>& arguments) {
  std::vector<fs::path> files;
  for (const std::string& argument : arguments) {
    const fs::path path = argument;
    if (!fs::is_directory(path)) {
      PS_CHECK(fs::is_regular_file(path), "--scan {}: no such file or directory", argument);
      files.push_back(path);
      continue;
    }
    const fs::path dir = fs::is_directory(path / "velodyne") ? path / "velodyne" : path;
    std::vector<fs::path> found;
    for (const fs::directory_entry& e : fs::directory_iterator(dir))
      if (e.is_regular_file() && !point_file_suffix(e.path()).empty()) found.push_back(e.path());
    PS_CHECK(!found.empty(), "--scan {}: no point files (.bin, .pcd, .ply, .npy, .pcd.bin) in {}", argument,
             dir.string());
    std::sort(found.begin(), found.end());
    files.insert(files.end(), found.begin(), found.end());
  }
  return files;
}

// One scan's results, written as PREFIX.u8, PREFIX.png and (with probabilities) PREFIX.f16.
struct Result {
  Tensor<uint8_t> labels;
  Tensor<float> probabilities;
};

void write_result(const std::string& prefix, const Result& r, bool png) {
  const ClassTable classes = ClassTable::defaults();
  write_label_map(prefix + ".u8", r.labels, classes);
  if (png) write_label_map(prefix + ".png", r.labels, classes);
  if (r.probabilities.numel() > 0) {
    std::vector<uint16_t> half(static_cast<size_t>(r.probabilities.numel()));
    for (size_t i = 0; i < half.size(); ++i)
      half[i] = weights::float_to_f16_bits(r.probabilities[static_cast<int64_t>(i)]);
    write_file_atomic(prefix + ".f16", half.data(), half.size() * sizeof(uint16_t));
  }
}

void run_infer(const InferArgs& a) {
  const std::vector<fs::path> files = scan_files(a.scans);
  const bool single = files.size() == 1 && !fs::is_directory(a.scans.front());
  if (!single) {
    PS_CHECK(!fs::exists(a.out) || fs::is_directory(a.out),
             "--out {}: several scans are written into a directory, and this is a file", a.out);
    fs::create_directories(a.out);
  }
  const PointFormat format = parse_point_format(a.format);
  auto segmenter = open_for(a.weights, a.config, a.device, a.mask_unobserved, a.flips);
  segmenter->set_input_mapping(input_mapping(a, segmenter->input_mapping()));
  if (!segmenter->input_mapping().is_identity())
    fmt::print(stderr, "input mapping: {}\n", segmenter->input_mapping().describe());
  const GridSpec& grid = segmenter->model().grid;
  const auto prefix_of = [&](const fs::path& file) {
    return single ? a.out : (fs::path(a.out) / file.stem()).string();
  };
  const auto make_result = [&] {
    Result r{Tensor<uint8_t>({grid.height(), grid.width()}), {}};
    if (a.probabilities) r.probabilities = Tensor<float>({12, grid.height(), grid.width()});
    return r;
  };
  // Two result slots: one being written while the next scan runs into the other.
  Result slots[2] = {make_result(), make_result()};
  Progress progress("infer", static_cast<int64_t>(files.size()), "scans");
  const auto started = std::chrono::steady_clock::now();
  double segment_seconds = 0;
  int64_t points = 0;
  std::future<Scan> next = std::async(std::launch::async, [&] { return read_points(files[0], format); });
  std::future<void> writing;
  for (size_t i = 0; i < files.size(); ++i) {
    const Scan scan = next.get();
    if (i + 1 < files.size()) next = std::async(std::launch::async, [&, i] { return read_points(files[i + 1], format); });
    Result& result = slots[i % 2];
    const auto t0 = std::chrono::steady_clock::now();
    segmenter->segment(scan.points, result.labels.data(),
                       a.probabilities ? result.probabilities.data() : nullptr);
    segment_seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    points += static_cast<int64_t>(scan.points.size());
    if (writing.valid()) writing.get();  // the other slot is free again
    writing = std::async(std::launch::async,
                         [&, i, prefix = prefix_of(files[i])] { write_result(prefix, slots[i % 2], !a.no_png); });
    if (single) {
      writing.get();
      fmt::print("{}: {} points -> {}.u8{}{}\n", files[i].string(), scan.points.size(), a.out,
                 a.no_png ? "" : fmt::format(", {}.png", a.out),
                 a.probabilities ? fmt::format(", {}.f16 (12 x H x W float16)", a.out) : "");
      return;
    }
    progress.update(static_cast<int64_t>(i) + 1, fmt::format("{:.1f} ms a scan on {}",
                                                              1e3 * segment_seconds / static_cast<double>(i + 1),
                                                              segmenter->backend().name()));
  }
  writing.get();
  progress.finish();
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  const double n = static_cast<double>(files.size());
  fmt::print("{} scans ({:.0f} points each on average) -> {}: {:.2f} scans/s end to end ({:.1f} s), segment "
             "{:.1f} ms a scan on {} (reading and writing overlap it)\n",
             files.size(), static_cast<double>(points) / n, a.out, n / wall, wall, 1e3 * segment_seconds / n,
             segmenter->backend().name());
}

void run_render(const RenderArgs& a) {
  require_extension(a.out, {".png"}, "--out");
  const Font font(find_font());  // before any work: a missing font is reported first
  GridSpec grid;
  std::unique_ptr<ScanSegmenter> segmenter;
  if (!a.weights.empty()) {
    segmenter = open_for(a.weights, a.config, a.device, false, a.flips);
    grid = segmenter->model().grid;
  }
  // Every panel in the model's frame: the sequence maps its points and poses as the config says.
  const Sequence seq(a.data, a.sequence, segmenter ? segmenter->input_mapping() : InputMapping{});
  const size_t index = scan_index(seq, a.scan);
  const Scan scan = seq.load(index);
  const ClassTable classes = ClassTable::defaults();
  const std::string masked = a.mask_unobserved ? ", unobserved cells black" : "";
  const bool labelled = !scan.labels.empty() && scan.labels.size() == scan.points.size();
  std::vector<TitledPanel> panels;
  panels.push_back({labelled ? "Points (class colours; unlabelled points grey)"
                             : "Points (grey by height: darker lower)",
                    render_points(scan.points, scan.labels, classes, grid)});
  const Tensor<uint32_t> observability =
      host::observability_map(host::observability_2d(scan.points, Eigen::Vector3d::Zero(), grid));
  panels.push_back({"Observability (rays through or ending in a cell, log scale)", render_observability(observability)});
  Tensor<uint8_t> mask(observability.shape());
  for (int64_t i = 0; i < mask.numel(); ++i) mask[i] = observability[i] > 0;
  if (segmenter) {
    Tensor<uint8_t> labels({grid.height(), grid.width()});
    segmenter->segment_mapped(scan.points, labels.data());
    ImageRgb prediction = render_label_map(labels, classes);
    if (a.mask_unobserved) apply_mask(prediction, mask);
    const std::string flips = a.flips > 1 ? fmt::format(", {} flips", a.flips) : "";
    panels.push_back({fmt::format("Prediction ({}, {}{}{})", fs::path(a.weights).filename().string(),
                                  segmenter->backend().name(), flips, masked),
                      std::move(prediction)});
  }
  if (seq.has_labels(index)) {
    GroundTruthSettings settings;
    settings.grid = grid;
    std::optional<Cache> cache;
    if (!a.cache.empty()) cache.emplace(a.cache);
    const GroundTruthBuilder builder(seq, classes, settings, cache);
    ImageRgb truth = render_label_map(builder.map(index, parse_ground_truth_kind(a.mode)), classes);
    if (a.mask_unobserved) apply_mask(truth, mask);
    panels.push_back({fmt::format("{} ground truth{}", a.mode == "dense" ? "Dense" : "Sparse", masked),
                      std::move(truth)});
  }
  const Figure figure = compose_figure(panels, classes, grid.cell, font);
  write_png_rgb(a.out, figure.image);
  fmt::print("{}: panels (top to bottom) points, observability{}{}, {} x {} pixels ({} a cell) -> {}\n",
             seq.scan_path(index).string(), segmenter ? ", prediction" : "",
             seq.has_labels(index) ? ", " + a.mode + " ground truth" : "", figure.image.width,
             figure.image.height, figure.scale, a.out);
}

}  // namespace

void add_infer(CLI::App& app) {
  auto a = std::make_shared<InferArgs>();
  CLI::App* cmd = app.add_subcommand(
      "infer",
      "Scans -> label maps: one scan -> PREFIX.u8 (class ids, H x W), PREFIX.png (colors); several "
      "files or directories -> OUT/NNNNNN.u8, .png, with progress and throughput");
  cmd->add_option("--weights", a->weights, "checkpoint (.safetensors); a weights-only one too")->required();
  cmd->add_option("--scan", a->scans,
                  "point file(s) (.bin KITTI, .pcd, .ply, .npy, .pcd.bin nuScenes: docs/formats.md), or directories "
                  "of them (a sequence directory: its velodyne/)")
      ->required();
  cmd->add_option("--format", a->format, "the point files' format: auto (by extension), kitti, pcd, ply, npy, nuscenes")
      ->check(CLI::IsMember({"auto", "kitti", "pcd", "ply", "npy", "nuscenes"}));
  const char* mapping = "Input mapping (replaces the run config's input: section)";
  cmd->add_option("--reflectance-scale", a->reflectance_scale,
                  "reflectance = clamp(scale x r + offset, 0, 1), e.g. 0.00392157 for 0..255 intensities")
      ->group(mapping);
  cmd->add_option("--reflectance-offset", a->reflectance_offset, "see --reflectance-scale (default 0)")->group(mapping);
  cmd->add_flag("--no-reflectance", a->no_reflectance, "the sensor gives no reflectance: every point gets 0")
      ->group(mapping);
  cmd->add_option("--transform", a->transform,
                  "\"16 numbers\": row-major 4 x 4 from the sensor's frame into the model's (x forward, z up)")
      ->expected(16)
      ->delimiter(' ')
      ->group(mapping);
  cmd->add_option("--height", a->height, "metres added to z (after the rotation)")->group(mapping);
  cmd->add_option("--roll", a->roll, "degrees about x: p' = Rz(yaw) Ry(pitch) Rx(roll) p + (0, 0, height)")
      ->group(mapping);
  cmd->add_option("--pitch", a->pitch, "degrees about y")->group(mapping);
  cmd->add_option("--yaw", a->yaw, "degrees about z")->group(mapping);
  cmd->add_option("--out", a->out, "output prefix (one scan) or directory (several)")->required();
  cmd->add_flag("--probabilities", a->probabilities, "also .f16: softmax probabilities, 12 x H x W float16");
  cmd->add_flag("--mask-unobserved", a->mask_unobserved, "label cells no ray observed as 0 (unlabeled)");
  cmd->add_flag("--no-png", a->no_png, "write no .png pictures (the class ids alone)");
  cmd->add_option("--config", a->config,
                  "run config (default: the one stored in the checkpoint; for a weights-only file its "
                  "tensor shapes on the paper's grid)");
  add_device_options(cmd, a->device);
  add_flips_option(cmd, a->flips);
  cmd->callback([a] { run_infer(*a); });

  auto r = std::make_shared<RenderArgs>();
  CLI::App* rc = app.add_subcommand("render",
                                    "PNG panels like the paper's Fig. 3: points, observability, prediction (with "
                                    "--weights), ground truth; titled, at least 1000 pixels wide, with a class "
                                    "legend and a scale bar");
  rc->add_option("--data", r->data, "SemanticKITTI root")->required();
  rc->add_option("--sequence", r->sequence, "sequence number")->required();
  rc->add_option("--scan", r->scan, "scan (frame) number")->required();
  rc->add_option("--out", r->out, "output .png")->required();
  rc->add_option("--weights", r->weights, "checkpoint for the prediction panel");
  rc->add_option("--config", r->config, "run config (default: the one stored in the checkpoint)");
  rc->add_option("--mode", r->mode, "ground truth: sparse or dense")->check(CLI::IsMember({"sparse", "dense"}));
  rc->add_flag("--mask-unobserved", r->mask_unobserved, "black out cells no ray observed");
  add_device_options(rc, r->device);
  add_flips_option(rc, r->flips);
  rc->add_option("--cache", r->cache, "ground-truth cache directory");
  rc->callback([r] { run_render(*r); });
}

}  // namespace pillarseg::cli
