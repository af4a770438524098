// The PyTorch peer of the model benchmarks: bench/peer/pytorch_peer.py --serve in its own
// process, one step per command on its stdin, run by --peer_python.
#pragma once

#include <sys/types.h>

#include <cstdio>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "bench/support/step_timing.hpp"

namespace pillarseg::bench {

// "key=value key=value" after the first word of a PEER line -> map.
std::map<std::string, std::string> parse_fields(const std::string& line);

// A running `pytorch_peer.py --serve`: each command written to its stdin is answered by one
// PEER_STEP line with the wall and CPU time of the step it ran. Everything else it prints
// (stderr merged) is kept: the final PEER line, PEER_PROFILE lines, error messages.
class PeerProcess {
 public:
  // Starts the peer with --threads T --serve `arguments` and waits until it has warmed up.
  explicit PeerProcess(const std::vector<std::string>& arguments);
  ~PeerProcess() { finish(); }
  PeerProcess(const PeerProcess&) = delete;
  PeerProcess& operator=(const PeerProcess&) = delete;

  bool ok() const { return failure_.empty(); }
  const std::string& failure() const { return failure_; }
  const std::string& summary() const { return summary_; }  // the final PEER line
  const std::vector<std::string>& lines() const { return lines_; }

  // Runs one command; returns its wall seconds and adds its times to `times`, or returns
  // nullopt once the peer has failed.
  std::optional<double> step(const std::string& command, StepTimes& times);

  // Closes the peer's stdin (it then prints its PEER line and exits) and waits for it.
  void finish();

 private:
  // Reads lines into lines_ until one starts with `prefix` (returned in `line`, not kept);
  // false at the end of the output. to_end: read everything.
  bool read_until(const std::string& prefix, std::string& line, bool to_end = false);

  pid_t pid_ = -1;
  FILE* to_peer_ = nullptr;
  FILE* from_peer_ = nullptr;
  std::vector<std::string> lines_;
  std::string summary_, failure_;
};

}  // namespace pillarseg::bench
