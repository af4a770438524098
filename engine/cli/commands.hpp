// The pillarseg subcommands; each registers itself on the CLI11 app and runs when selected.
#pragma once

#include <CLI/CLI.hpp>

namespace pillarseg::cli {

void add_simulate(CLI::App& app);
void add_gt(CLI::App& app);
void add_info(CLI::App& app);
void add_maps(CLI::App& app);
void add_train(CLI::App& app);
void add_infer(CLI::App& app);
void add_bench(CLI::App& app);
void add_plot(CLI::App& app);
void add_calibrate(CLI::App& app);

}  // namespace pillarseg::cli
