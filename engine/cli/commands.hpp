// The pillarseg subcommands; each registers itself on the CLI11 app and runs when selected.
#pragma once

#include <CLI/CLI.hpp>

namespace pillarseg::cli {

// pillarseg gt: ground truth of one scan (PNG or .u8) or the cache of a sequence.
void add_gt(CLI::App& app);

}  // namespace pillarseg::cli
