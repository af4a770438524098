// `pillarseg gt`: sparse or dense ground truth of one scan as a color PNG or raw class ids
// (.u8), or the cache of a whole sequence: run_gt_command (engine/cli/gt_command.hpp) and its
// command line.
#include <fmt/format.h>

#include <algorithm>
#include <memory>
#include <string>

#include "core/error.hpp"
#include "core/io.hpp"
#include "engine/cli/commands.hpp"
#include "engine/cli/gt_command.hpp"
#include "engine/data/class_table_yaml.hpp"
#include "engine/render/label_map.hpp"

namespace pillarseg {

namespace fs = std::filesystem;

std::string run_gt_command(const GtCommandOptions& options) {
  if (options.scan) {
    PS_CHECK(!options.out.empty(), "--out: required with --scan (a .png or .u8 path)");
    const std::string extension = lower_extension(options.out);
    PS_CHECK(extension == ".png" || extension == ".u8",
             "--out {}: unknown extension '{}', expected .png (color map) or .u8 (raw class ids)",
             options.out.string(), extension);
  } else {
    PS_CHECK(options.out.empty(),
             "--out {}: needs --scan (without --scan, gt fills the cache for the whole sequence)",
             options.out.string());
  }
  PS_CHECK(fs::is_directory(options.data_root / "sequences"),
           "--data {}: no directory {} (expected a SemanticKITTI ROOT with sequences/SS/velodyne)",
           options.data_root.string(), (options.data_root / "sequences").string());
  PS_CHECK(options.sequence >= 0 && options.sequence <= 99, "--sequence {}: expected 0..99",
           options.sequence);
  const fs::path sequence_dir = options.data_root / "sequences" / sequence_name(options.sequence);
  PS_CHECK(fs::is_directory(sequence_dir / "velodyne"), "--sequence {}: no directory {}",
           sequence_name(options.sequence), (sequence_dir / "velodyne").string());

  ClassTable table = options.classes_yaml.empty()
                         ? ClassTable::defaults()
                         : load_class_table(options.classes_yaml.string());
  const fs::path cache_dir =
      options.cache_dir.empty() ? default_cache_dir(options.data_root) : options.cache_dir;
  Sequence sequence(options.data_root, options.sequence);
  GroundTruthSettings settings;
  settings.grid = options.grid;

  if (!options.scan) {
    const size_t count = sequence.size();
    const GroundTruthBuilder builder(std::move(sequence), std::move(table), settings,
                                     Cache(cache_dir));
    const GroundTruthBuilder::BuildCounts counts =
        builder.build_all(options.kind, options.show_progress);
    return fmt::format(
        "sequence {}: {} ground truth of {} scans in {} (computed {}, already cached {})",
        sequence_name(options.sequence), to_string(options.kind), count, cache_dir.string(),
        counts.computed, counts.cached);
  }

  const int frame = *options.scan;
  size_t index = sequence.size();
  for (size_t i = 0; i < sequence.size(); ++i)
    if (sequence.frame(i) == frame) index = i;
  PS_CHECK(index < sequence.size(), "--scan {}: out of range, sequence {} has {}", frame,
           sequence_name(options.sequence),
           sequence.size() == 0
               ? std::string("no scans")
               : fmt::format("scans {:06}..{:06} ({} files)", sequence.frame(0),
                             sequence.frame(sequence.size() - 1), sequence.size()));
  const GroundTruthBuilder builder(std::move(sequence), table, settings, Cache(cache_dir));
  bool from_cache = false;
  const Tensor<uint8_t> map = builder.map(index, options.kind, &from_cache);
  write_label_map(options.out, map, table);
  const int64_t labelled = std::count_if(map.data(), map.data() + map.numel(),
                                         [](uint8_t k) { return k != kUnlabeled; });
  return fmt::format(
      "wrote {}: {} ground truth of sequence {} scan {:06}, {} x {} cells, {} labelled ({})",
      options.out.string(), to_string(options.kind), sequence_name(options.sequence), frame,
      map.dim(1), map.dim(0), labelled, from_cache ? "from the cache" : "computed");
}

}  // namespace pillarseg

namespace pillarseg::cli {

void add_gt(CLI::App& app) {
  CLI::App* cmd = app.add_subcommand(
      "gt",
      "Build ground truth: with --scan, write one scan's map (PNG: top view, +x right, +y up; "
      ".u8: H rows of W class ids, row iy); without it, fill the cache for the whole sequence");
  auto options = std::make_shared<GtCommandOptions>();
  auto mode = std::make_shared<std::string>("sparse");
  auto scan = std::make_shared<int>(0);
  cmd->add_option("--data", options->data_root, "SemanticKITTI ROOT (holds sequences/SS)")
      ->required();
  cmd->add_option("--sequence", options->sequence, "sequence number SS")->required();
  CLI::Option* scan_option =
      cmd->add_option("--scan", *scan,
                      "frame number NNNNNN of one scan; omit to build the whole sequence")
          ->check(CLI::NonNegativeNumber);
  cmd->add_option("--mode", *mode, "sparse or dense")->check(CLI::IsMember({"sparse", "dense"}));
  cmd->add_option("--out", options->out, "output map: .png (color) or .u8 (raw class ids)");
  cmd->add_option("--cache", options->cache_dir,
                  "cache directory (default: ROOT/pillarseg_cache if writable, else "
                  "$XDG_CACHE_HOME/pillarseg or ~/.cache/pillarseg)");
  cmd->add_option("--classes", options->classes_yaml,
                  "class table YAML (default: DESIGN.md's table)")
      ->check(CLI::ExistingFile);
  cmd->callback([options, mode, scan, scan_option] {
    options->kind = parse_ground_truth_kind(*mode);
    if (scan_option->count() > 0) options->scan = *scan;
    fmt::print("{}\n", run_gt_command(*options));
  });
}

}  // namespace pillarseg::cli
