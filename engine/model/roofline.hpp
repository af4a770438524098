// A roofline bound for the op graph's nodes on a named GPU: a node cannot take less than its
// FLOPs at the peak rate of the units it runs on (the tensor cores' dense 16-bit rate for the
// BF16/FP16 convolutions, their dense INT8 rate for the INT8 ones, the CUDA cores' FP32 rate for
// everything else) nor less than its bytes
// (Graph::node_bytes: every tensor read and written once) at the memory bandwidth. The sum over
// the nodes is a lower bound on the network's time there, not a prediction: kernels reach a
// share of either peak, caches can only help by less than the tensors' own sizes, and launch
// gaps come on top. `pillarseg bench --ops --roofline GPU` prints it beside the measured times.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace pillarseg {

struct GpuPeaks {
  std::string name;
  double fp32_tflops = 0;  // CUDA cores, FMA = 2 flops
  double half_tflops = 0;  // tensor cores, dense BF16/FP16 with FP32 accumulation
  double int8_tops = 0;    // tensor cores, dense INT8 with INT32 accumulation (custom: 2 x half)
  double tb_per_s = 0;     // memory bandwidth, 10^12 bytes per second
  std::string source;      // where the figures come from
};

// The GPUs the table knows (datasheet figures, boost clocks, no sparsity).
const std::vector<GpuPeaks>& known_gpus();

// A GPU by name (case-insensitive: h200, h100-sxm, ...) or "custom:FP32:HALF:TB" (TFLOP/s,
// TFLOP/s, TB/s); throws pillarseg::Error naming the argument and the known names.
GpuPeaks parse_gpu(const std::string& spec);

struct RooflineBound {
  double compute_ms = 0, memory_ms = 0;
  double ms() const { return compute_ms > memory_ms ? compute_ms : memory_ms; }
  bool memory_bound() const { return memory_ms > compute_ms; }
};
// tensor_cores: at the 16-bit tensor rate, or with int8 the INT8 one; else the FP32 rate.
RooflineBound roofline_bound(double flops, double bytes, bool tensor_cores, const GpuPeaks& gpu, bool int8 = false);

class Graph;
// The bound of a whole graph: every node's (its flops, Graph::node_bytes at `pillar_rows`, the
// tensor cores for the 16-bit convolutions) summed, split into the nodes bound by compute and
// those bound by memory.
struct GraphBound {
  double compute_ms = 0, memory_ms = 0;
  double ms() const { return compute_ms + memory_ms; }
};
GraphBound graph_bound(const Graph& graph, int64_t pillar_rows, const GpuPeaks& gpu);

}  // namespace pillarseg
