// The inputs of the model benchmarks: the network at the paper's full size or the CPU configs'
// small one, the decorated pillars of simulated scans (or of --scan) and their sparse ground
// truth, and the same arrays as raw files for the PyTorch peer.
#pragma once

#include <array>
#include <cstdint>
#include <filesystem>
#include <string>

#include "core/tensor.hpp"
#include "engine/model/config.hpp"
#include "engine/model/pillarsegnet.hpp"

namespace pillarseg::bench {

constexpr uint64_t kSimulatorSeed = 1;
constexpr double kGradClip = 10.0;
// Sparse ground truth coefficients per class id 0..12 (DESIGN.md section 3).
constexpr std::array<float, 13> kCoefficients = {0, 2, 8, 8, 8, 1, 1, 1, 1, 1, 1, 1, 1};

struct SizeSetup {
  std::string size;
  ModelConfig config;
  int batch = 1;
  ModelBatch inputs;                  // pillar_points (P, N, 10), pillar_cells (P, 3)
  Tensor<uint8_t> labels;             // (B, H, W)
  std::filesystem::path peer_inputs;  // the same arrays as raw files for the PyTorch peer
};

// full: the paper's (grid 1000 x 500 cells of 0.1 m, C = b = 64, depth 4); small: make demo's
// (configs/small_cpu.yaml): 0.4 m cells, C = 32, b = 16.
ModelConfig config_of(const std::string& size, bool transposed);

// The inputs of `size` (full: batch 1; small: batch 2), made on first use and kept.
const SizeSetup& setup(const std::string& size);

// Removes the peer's input files of every setup made.
void remove_peer_inputs();

}  // namespace pillarseg::bench
