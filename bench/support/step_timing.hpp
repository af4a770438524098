// Timing of benchmark steps on a shared machine: wall and process CPU time per step, medians,
// the median ratio of two series measured alternately, and the process's peak resident memory.
#pragma once

#include <sys/resource.h>
#include <time.h>

#include <algorithm>
#include <chrono>
#include <fstream>
#include <vector>

namespace pillarseg::bench {

using Clock = std::chrono::steady_clock;

// CPU time of this process, all threads, in seconds.
inline double process_cpu_seconds() {
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}

inline double median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  const size_t n = v.size();
  return n % 2 == 1 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

// Wall and process CPU seconds of each timed step.
struct StepTimes {
  std::vector<double> wall, cpu;
  double wall_median() const { return median(wall); }
  double cpu_median() const { return median(cpu); }
  void add(double wall_seconds, double cpu_seconds) {
    wall.push_back(wall_seconds);
    cpu.push_back(cpu_seconds);
  }
};

// Runs step() once, adds its times to `times` and returns its wall seconds.
template <class Step>
double time_once(StepTimes& times, Step&& step) {
  const Clock::time_point start = Clock::now();
  const double cpu_start = process_cpu_seconds();
  step();
  const double cpu = process_cpu_seconds() - cpu_start;
  times.add(std::chrono::duration<double>(Clock::now() - start).count(), cpu);
  return times.wall.back();
}

// Median over steps i of a[i] / b[i]: the ratio of two step series measured alternately.
inline double median_ratio(const std::vector<double>& a, const std::vector<double>& b) {
  std::vector<double> ratios;
  for (size_t i = 0; i < std::min(a.size(), b.size()); ++i) ratios.push_back(a[i] / b[i]);
  return median(ratios);
}

// Resets the process's RSS high-water mark (Linux: writing 5 to /proc/self/clear_refs), so that
// ru_maxrss afterwards is the peak of what runs from now on. False where that is not possible.
inline bool reset_peak_rss() {
  std::ofstream clear("/proc/self/clear_refs");
  clear << "5";
  clear.flush();
  return static_cast<bool>(clear);
}

inline double peak_rss_mb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return static_cast<double>(usage.ru_maxrss) / 1024.0;  // ru_maxrss is in KiB
}

}  // namespace pillarseg::bench
