// Progress: a one-line display on stderr for long work: count, rate, ETA and an optional
// message (e.g. the loss). Redraws at most every 0.2 s; prints plain lines when stderr is not
// a terminal (CI logs), at most every 5 s.
#pragma once

#include <chrono>
#include <cstdint>
#include <string>

namespace pillarseg {

class Progress {
 public:
  Progress(std::string label, int64_t total, std::string unit = "it");
  ~Progress();
  void update(int64_t done, const std::string& message = "");
  void finish(const std::string& message = "");

 private:
  void draw(bool final);
  std::string label_, unit_, message_;
  int64_t total_, done_ = 0;
  bool tty_, finished_ = false;
  std::chrono::steady_clock::time_point start_, last_draw_;
};

std::string format_duration(double seconds);

}  // namespace pillarseg
