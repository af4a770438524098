// Reporting helpers of the CPU model benchmarks: the Google Benchmark counters of a case (rates,
// medians, the ratio to the PyTorch peer) and the cells of the summary tables.
#pragma once

#include <benchmark/benchmark.h>
#include <fmt/format.h>

#include <optional>
#include <string>
#include <vector>

#include "bench/support/step_timing.hpp"
#include "core/parallel.hpp"

namespace pillarseg::bench {

inline void set_rate_counters(benchmark::State& state, double flops, const StepTimes& t) {
  state.counters["GFLOP"] = flops * 1e-9;
  state.counters["median_ms"] = t.wall_median() * 1e3;
  state.counters["GFLOP/s"] = flops * 1e-9 / t.wall_median();
  state.counters["cpu_ms"] = t.cpu_median() * 1e3;
  state.counters["GFLOP/cpu_s"] = flops * 1e-9 / t.cpu_median();
  state.counters["threads"] = num_threads();
}

// Adds PyTorch's median and the median per-step ratio ours / PyTorch to the counters.
inline void set_peer_counters(benchmark::State& state, const StepTimes& ours, const StepTimes& torch) {
  if (torch.wall.empty()) return;
  state.counters["torch_ms"] = torch.wall_median() * 1e3;
  state.counters["ours/torch"] = median_ratio(ours.wall, torch.wall);
  state.counters["ours/torch_cpu"] = median_ratio(ours.cpu, torch.cpu);
}

// ---- table cells ----

inline std::string fixed(const std::optional<double>& v, int decimals) {
  return v ? fmt::format("{:.{}f}", *v, decimals) : std::string("-");
}

inline std::optional<double> wall_ms(const StepTimes& t) {
  return t.wall.empty() ? std::nullopt : std::optional<double>(t.wall_median() * 1e3);
}

inline std::optional<double> cpu_ms(const StepTimes& t) {
  return t.cpu.empty() ? std::nullopt : std::optional<double>(t.cpu_median() * 1e3);
}

inline std::string wall_list(const StepTimes& t) {
  std::string s;
  for (double v : t.wall) s += fmt::format("{}{:.0f}", s.empty() ? "" : ",", v * 1e3);
  return s.empty() ? std::string("-") : s;
}

inline std::string ratio(const std::vector<double>& ours, const std::vector<double>& torch) {
  return ours.empty() || torch.empty() ? std::string("-")
                                       : fmt::format("{:.2f}", median_ratio(ours, torch));
}

}  // namespace pillarseg::bench
