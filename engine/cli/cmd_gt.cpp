// `pillarseg gt`: sparse or dense ground truth of one scan as a color PNG or raw class ids
// (.u8), or the cache of a whole sequence. The work is run_gt_command
// (engine/data/ground_truth.hpp); this file only maps the command line onto its options.
#include <fmt/format.h>

#include <memory>
#include <string>

#include "engine/cli/commands.hpp"
#include "engine/data/ground_truth.hpp"

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
