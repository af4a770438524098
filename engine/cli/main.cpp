// pillarseg: the command line. Errors a user can cause print one line naming the file or
// argument and exit with status 1; a bad command line exits with CLI11's status.
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <cstdio>
#include <exception>

#include "core/error.hpp"
#include "core/parallel.hpp"
#include "engine/cli/commands.hpp"
#include "engine/cuda/install.hpp"

int main(int argc, char** argv) {
  // --device cuda runs the kernels on a GPU, --device emu on the CUDA emulation (engine/cuda/).
#if defined(PILLARSEG_WITH_CUDA_BACKEND)
  pillarseg::install_cuda_backend();
#endif
  pillarseg::install_emulated_cuda_backend();
  CLI::App app{"pillarseg: dense top-view semantic grid maps from one LiDAR sweep (PillarSegNet)"};
  app.require_subcommand(1);
  int threads = 0;
  std::string log_level = "info";
  app.add_option("--threads", threads, "CPU threads (0: all hardware threads)")->check(CLI::NonNegativeNumber);
  app.add_option("--log-level", log_level, "trace, debug, info, warn, error")
      ->check(CLI::IsMember({"trace", "debug", "info", "warn", "error"}));
  app.parse_complete_callback([&] {
    pillarseg::set_num_threads(threads);
    spdlog::set_level(spdlog::level::from_str(log_level));
    spdlog::set_pattern("[%l] %v");
  });

  pillarseg::cli::add_simulate(app);
  pillarseg::cli::add_gt(app);
  pillarseg::cli::add_maps(app);
  pillarseg::cli::add_train(app);
  pillarseg::cli::add_infer(app);
  pillarseg::cli::add_bench(app);
  pillarseg::cli::add_plot(app);
  pillarseg::cli::add_calibrate(app);
  pillarseg::cli::add_info(app);

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e);
  } catch (const pillarseg::Error& e) {
    std::fprintf(stderr, "pillarseg: error: %s\n", e.what());
    return 1;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "pillarseg: unexpected error: %s\n", e.what());
    return 2;
  }
  return 0;
}
