// The own flags of bench_model and bench_conv_layers (Google Benchmark's, such as
// --benchmark_filter=REGEX, work as well):
//   --threads=T (default 0: all hardware threads)  --reps=R (timed steps per model case, 1)
//   --layer_reps=R (per conv layer and GEMM, 1)  --small (add the small size)  --no_peer (skip
//   PyTorch)  --peer_profile (print PyTorch's time by op, from one more step under its profiler)
//   --scan=PATH.bin (a SemanticKITTI scan; labels from ../labels/NNNNNN.label)
//   --peer_python=PATH (default /usr/bin/python3)  --peer_script=PATH (default
//   bench/peer/pytorch_peer.py)
#pragma once

#include <filesystem>
#include <functional>
#include <string>

namespace pillarseg::bench {

struct Options {
  int threads = 0;  // 0: all hardware threads
  int reps = 1;
  int layer_reps = 1;
  bool small = false;
  std::filesystem::path scan;  // empty: simulated scans
  bool peer = true;
  bool peer_profile = false;
  std::string peer_python = "/usr/bin/python3";
  std::filesystem::path peer_script =
      std::filesystem::path(__FILE__).parent_path().parent_path() / "peer" / "pytorch_peer.py";
};

// The options of this run (parse_options() sets them).
Options& options();

// Takes this benchmark's own flags out of argv (Google Benchmark rejects flags it does not know).
Options parse_options(int& argc, char** argv);

// The main of a model benchmark named `name`: its own flags parsed into options(), the threads
// set, Google Benchmark's flags, `registration` registering the benchmarks, the runs, `report`
// printing the tables, and `cleanup` (also after an error, which is printed). A peer process that
// dies while written to is an error, not a SIGPIPE. Returns the exit status.
int model_benchmark_main(int argc, char** argv, const char* name, const std::function<void()>& registration,
                         const std::function<void()>& report, const std::function<void()>& cleanup);

}  // namespace pillarseg::bench
