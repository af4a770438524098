// pillarseg simulate: writes procedural urban sequences in the SemanticKITTI layout (the
// embedded default data set; see engine/sim/simulate.hpp).
#include <memory>

#include "engine/cli/commands.hpp"
#include "engine/sim/simulate.hpp"

namespace pillarseg::cli {

void add_simulate(CLI::App& app) {
  auto options = std::make_shared<sim::SimulateOptions>();
  CLI::App* cmd = app.add_subcommand("simulate",
                                     "Write simulated SemanticKITTI sequences: streets, traffic, a "
                                     "64-beam LiDAR, poses and labels");
  cmd->add_option("--out", options->out, "output root; sequences/SS/ are written under it")
      ->required();
  cmd->add_option("--sequences", options->sequences, "number of sequences")
      ->capture_default_str()
      ->check(CLI::Range(1, 100));
  cmd->add_option("--scans", options->scans, "scans per sequence (10 Hz)")
      ->capture_default_str()
      ->check(CLI::Range(1, 1000000));
  cmd->add_option("--seed", options->seed,
                  "seed of the data set; each sequence's seed derives from it and its id")
      ->capture_default_str();
  cmd->add_option("--first-sequence", options->first_sequence, "id of the first sequence written")
      ->capture_default_str()
      ->check(CLI::Range(0, 99));
  cmd->add_option("--points-per-scan", options->points_per_scan, "target returns per scan")
      ->capture_default_str()
      ->check(CLI::Range(int64_t{10000}, int64_t{2000000}));
  cmd->callback([options] { sim::simulate(*options); });
}

}  // namespace pillarseg::cli
