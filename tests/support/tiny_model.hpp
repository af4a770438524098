// A tiny PillarSegNet and random inputs for the model-level tests (test_model, test_cuda_backend);
// defined in test_support.cpp.
#pragma once

#include <array>
#include <cstdint>

#include "engine/model/pillarsegnet.hpp"

namespace pillarseg::test {

// A tiny PillarSegNet for model-level tests: a 24 x 16 grid of 0.1 m cells, 4 layers, N = 3,
// C = 4, Q = 3, base width 4, depth 2.
ModelConfig tiny_config(OccupancyInput occupancy = OccupancyInput::None, bool transposed = false,
                        bool grid_map = false);

// One batch of network inputs with labels for a config.
struct TinyData {
  ModelBatch batch;
  Tensor<uint8_t> labels;
};

// Pillars over distinct cells of a (B, H, W) grid (each cell with probability `density`), each
// with 1..N random points; random occupancy and grid-map layers where the config has them;
// labels 0..12.
TinyData tiny_data(const ModelConfig& c, int B, uint64_t seed, double density = 0.3);

// Loss coefficients per class id 0..12 (the paper's sparse ones).
inline constexpr std::array<float, 13> kCoefficients = {0, 2, 8, 8, 8, 1, 1, 1, 1, 1, 1, 1, 1};

}  // namespace pillarseg::test
