#include "engine/model/roofline.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cctype>
#include <charconv>

#include "core/error.hpp"
#include "engine/model/graph.hpp"

namespace pillarseg {

const std::vector<GpuPeaks>& known_gpus() {
  // Orin's tensor rate is not in its datasheet: SMs x clock x the dense FP16/BF16 rate of sm_87
  // with FP32 accumulation (2,048 flops per clock per SM), as bench_kernels_conv derives a
  // device's peak.
  static const std::vector<GpuPeaks> gpus = {
      {"h200", 67, 989, 1979, 4.8, "NVIDIA H200 SXM datasheet"},
      {"h100-sxm", 67, 989, 1979, 3.35, "NVIDIA H100 SXM datasheet"},
      {"h100-pcie", 51, 756, 1513, 2.0, "NVIDIA H100 PCIe datasheet"},
      {"a100-sxm", 19.5, 312, 624, 2.039, "NVIDIA A100 80GB SXM datasheet"},
      {"l4", 30.3, 121, 242.5, 0.3, "NVIDIA L4 datasheet"},
      {"rtx4090", 82.6, 165.2, 660.6, 1.008, "NVIDIA Ada whitepaper (FP16 tensor with FP32 accumulation)"},
      {"orin-agx-64", 5.3, 42.6, 85.2, 0.2048,
       "Jetson AGX Orin 64GB datasheet (FP32, LPDDR5); tensor: 16 SMs x 1.3 GHz x 2,048 (INT8: x 4,096)"},
  };
  return gpus;
}

namespace {

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

std::string known_names() {
  std::string names;
  for (const GpuPeaks& g : known_gpus()) names += (names.empty() ? "" : ", ") + g.name;
  return names;
}

}  // namespace

GpuPeaks parse_gpu(const std::string& spec) {
  const std::string name = lower(spec);
  for (const GpuPeaks& g : known_gpus())
    if (g.name == name) return g;
  const std::string prefix = "custom:";
  PS_CHECK(name.rfind(prefix, 0) == 0,
           "--roofline {}: unknown GPU; known: {}, or custom:FP32_TFLOPS:HALF_TFLOPS:TB_PER_S",
           spec, known_names());
  double values[3] = {0, 0, 0};
  size_t at = prefix.size();
  for (int i = 0; i < 3; ++i) {
    const size_t end = i < 2 ? name.find(':', at) : name.size();
    PS_CHECK(end != std::string::npos,
             "--roofline {}: expected custom:FP32_TFLOPS:HALF_TFLOPS:TB_PER_S (three numbers)",
             spec);
    const char* first = name.data() + at;
    const char* last = name.data() + end;
    const auto [ptr, ec] = std::from_chars(first, last, values[i]);
    PS_CHECK(ec == std::errc() && ptr == last && values[i] > 0 && values[i] < 1e9,
             "--roofline {}: '{}' is not a positive number (expected "
             "custom:FP32_TFLOPS:HALF_TFLOPS:TB_PER_S)",
             spec, std::string(first, last));
    at = end + 1;
  }
  return GpuPeaks{spec, values[0], values[1], 2 * values[1], values[2], "given on the command line"};
}

RooflineBound roofline_bound(double flops, double bytes, bool tensor_cores, const GpuPeaks& gpu, bool int8) {
  const double tflops = tensor_cores ? (int8 ? gpu.int8_tops : gpu.half_tflops) : gpu.fp32_tflops;
  RooflineBound b;
  b.compute_ms = tflops > 0 ? flops / (tflops * 1e12) * 1e3 : 0.0;
  b.memory_ms = gpu.tb_per_s > 0 ? bytes / (gpu.tb_per_s * 1e12) * 1e3 : 0.0;
  return b;
}

GraphBound graph_bound(const Graph& graph, int64_t pillar_rows, const GpuPeaks& gpu) {
  GraphBound total;
  for (size_t i = 0; i < graph.size(); ++i) {
    const GraphNode& n = graph.nodes()[i];
    const RooflineBound b =
        roofline_bound(n.flops, static_cast<double>(graph.node_bytes(i, pillar_rows)),
                       on_matrix_units(graph, n), gpu, on_int8_units(graph, n));
    (b.memory_bound() ? total.memory_ms : total.compute_ms) += b.ms();
  }
  return total;
}

}  // namespace pillarseg
