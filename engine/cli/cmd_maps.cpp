// pillarseg observability / occupancy: the 2D observability map (ray counts per cell) and the
// 3D occupancy map of one scan, as pictures or raw arrays.
#include <fmt/format.h>

#include <cmath>

#include "core/io.hpp"
#include "engine/cli/cli_util.hpp"
#include "engine/cli/commands.hpp"
#include "engine/data/ground_truth.hpp"
#include "engine/render/render.hpp"
#include "engine/util/image.hpp"

namespace pillarseg::cli {

namespace {

struct MapArgs {
  std::string data, out, cache;
  int sequence = -1, scan = -1;
};

CLI::App* add_map_command(CLI::App& app, const std::string& name, const std::string& help, MapArgs& args) {
  CLI::App* cmd = app.add_subcommand(name, help);
  cmd->add_option("--data", args.data, "SemanticKITTI root (holds sequences/)")->required();
  cmd->add_option("--sequence", args.sequence, "sequence number")->required();
  cmd->add_option("--scan", args.scan, "scan (frame) number")->required();
  cmd->add_option("--out", args.out, "output file")->required();
  cmd->add_option("--cache", args.cache, "cache directory (default: beside the data, else ~/.cache/pillarseg)");
  return cmd;
}

// The scan's maps come through the ground-truth builder's cache.
GroundTruthBuilder builder_for(const MapArgs& args) {
  const Cache cache(args.cache.empty() ? default_cache_dir(args.data) : std::filesystem::path(args.cache));
  return GroundTruthBuilder(Sequence(args.data, args.sequence), ClassTable::defaults(), GroundTruthSettings{}, cache);
}

void run_observability(const MapArgs& args) {
  require_extension(args.out, {".png", ".u16"}, "--out");
  const GroundTruthBuilder builder = builder_for(args);
  const Sequence& seq = builder.sequence();
  const Tensor<uint32_t> counts = builder.observability(scan_index(seq, args.scan));
  if (lower_extension(args.out) == ".u16") {
    std::vector<uint16_t> raw(static_cast<size_t>(counts.numel()));
    for (int64_t i = 0; i < counts.numel(); ++i) raw[static_cast<size_t>(i)] = static_cast<uint16_t>(std::min<uint32_t>(counts[i], 65535));
    write_file_atomic(args.out, raw.data(), raw.size() * sizeof(uint16_t));
  } else {
    write_png_rgb(args.out, render_observability(counts));
  }
  int64_t observed = 0;
  for (uint32_t c : counts) observed += c > 0;
  fmt::print("{}: {} of {} cells observed -> {}\n", seq.scan_path(scan_index(seq, args.scan)).string(), observed,
             counts.numel(), args.out);
}

void run_occupancy(const MapArgs& args) {
  require_extension(args.out, {".png", ".f32"}, "--out");
  const GroundTruthBuilder builder = builder_for(args);
  const Sequence& seq = builder.sequence();
  const Tensor<float> prob = builder.occupancy(scan_index(seq, args.scan));
  if (lower_extension(args.out) == ".f32") {
    write_file_atomic(args.out, prob.data(), static_cast<size_t>(prob.numel()) * sizeof(float));
  } else {
    write_png_rgb(args.out, render_occupancy(prob));
  }
  fmt::print("{}: occupancy ({} layers x {} x {}) -> {}\n", seq.scan_path(scan_index(seq, args.scan)).string(),
             prob.dim(0), prob.dim(1), prob.dim(2), args.out);
}

}  // namespace

void add_maps(CLI::App& app) {
  auto obs = std::make_shared<MapArgs>();
  add_map_command(app, "observability",
                  "2D observability map of a scan: .png (log grey, +y up) or .u16 (raw counts, H rows of W)", *obs)
      ->callback([obs] { run_observability(*obs); });
  auto occ = std::make_shared<MapArgs>();
  add_map_command(app, "occupancy",
                  "3D occupancy map of a scan: .png (max over layers of |p - 0.5|) or .f32 (Z x H x W probabilities)",
                  *occ)
      ->callback([occ] { run_occupancy(*occ); });
}

}  // namespace pillarseg::cli
