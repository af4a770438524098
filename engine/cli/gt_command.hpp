// `pillarseg gt`: one scan's ground truth as a color PNG or raw class ids (.u8), or the cache of
// a whole sequence. Its options are the command line's; cmd_gt.cpp maps one onto the other.
#pragma once

#include <filesystem>
#include <optional>
#include <string>

#include "core/grid.hpp"
#include "engine/data/ground_truth.hpp"

namespace pillarseg {

// `pillarseg gt`.
struct GtCommandOptions {
  std::filesystem::path data_root;  // --data ROOT
  int sequence = -1;                // --sequence SS
  std::optional<int> scan;          // --scan N: frame number; none = the whole sequence
  GroundTruthKind kind = GroundTruthKind::sparse;  // --mode
  std::filesystem::path out;                       // --out PATH (.png or .u8), with --scan only
  std::filesystem::path cache_dir;     // --cache DIR; empty = default_cache_dir(data_root)
  std::filesystem::path classes_yaml;  // --classes FILE.yaml; empty = the default table
  GridSpec grid;
  bool show_progress = true;
};
// Writes one scan's map (--scan) or fills the cache for the whole sequence; returns the
// one-line report. Errors name the command-line argument at fault.
std::string run_gt_command(const GtCommandOptions& options);

}  // namespace pillarseg
