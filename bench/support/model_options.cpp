#include "bench/support/model_options.hpp"

#include <benchmark/benchmark.h>

#include <csignal>
#include <cstdio>
#include <exception>

#include "core/error.hpp"
#include "core/parallel.hpp"

namespace pillarseg::bench {

Options& options() {
  static Options o;
  return o;
}

Options parse_options(int& argc, char** argv) {
  Options o;
  int kept = 1;
  // The integer after "--name=" in arg, at least `minimum`.
  const auto int_value = [](const std::string& arg, int minimum) {
    const std::string text = arg.substr(arg.find('=') + 1);
    size_t used = 0;
    int v = 0;
    try {
      v = std::stoi(text, &used);
    } catch (const std::exception&) {
      used = 0;
    }
    PS_CHECK(used == text.size() && !text.empty() && v >= minimum,
             "{}: expected an integer >= {} after '=', got '{}'", arg, minimum, text);
    return v;
  };
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg.rfind("--threads=", 0) == 0) {
      o.threads = int_value(arg, 0);
    } else if (arg.rfind("--reps=", 0) == 0) {
      o.reps = int_value(arg, 1);
    } else if (arg.rfind("--layer_reps=", 0) == 0) {
      o.layer_reps = int_value(arg, 1);
    } else if (arg == "--small") {
      o.small = true;
    } else if (arg == "--no_peer") {
      o.peer = false;
    } else if (arg == "--peer_profile") {
      o.peer_profile = true;
    } else if (arg.rfind("--scan=", 0) == 0) {
      o.scan = arg.substr(7);
    } else if (arg.rfind("--peer_python=", 0) == 0) {
      o.peer_python = arg.substr(14);
    } else if (arg.rfind("--peer_script=", 0) == 0) {
      o.peer_script = arg.substr(14);
    } else {
      argv[kept++] = argv[i];
    }
  }
  argc = kept;
  return o;
}

int model_benchmark_main(int argc, char** argv, const char* name, const std::function<void()>& registration,
                         const std::function<void()>& report, const std::function<void()>& cleanup) {
  std::signal(SIGPIPE, SIG_IGN);
  try {
    options() = parse_options(argc, argv);
    set_num_threads(options().threads);
    benchmark::Initialize(&argc, argv);
    if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
    registration();
    benchmark::RunSpecifiedBenchmarks();
    report();
    cleanup();
    benchmark::Shutdown();
  } catch (const std::exception& e) {
    cleanup();
    std::fprintf(stderr, "%s: %s\n", name, e.what());
    return 1;
  }
  return 0;
}

}  // namespace pillarseg::bench
