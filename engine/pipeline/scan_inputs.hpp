// The network inputs of one scan (DESIGN.md sections 1 and 2): pillars with decorated points,
// the occupancy input (2D observability as log(1 + count), or the 3D occupancy probability),
// and the grid-map layers; and the batching of several scans into one ModelBatch.
#pragma once

#include <vector>

#include "core/eigen.hpp"
#include "core/point.hpp"
#include "core/rng.hpp"
#include "core/tensor.hpp"
#include "engine/model/config.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "host/pillar_gather.hpp"

namespace pillarseg {

struct ScanInputs {
  Tensor<float> pillar_points;   // (P, N, 10)
  Tensor<int32_t> pillar_cells;  // (P, 2): iy, ix
  Tensor<float> occupancy;       // (1 or Z, H, W) when the model has an occupancy stream
  Tensor<float> grid_map;        // (6, H, W) when the model has the grid-map input
  Tensor<uint32_t>
      observability;  // (H, W) ray counts, when computed (occupancy or grid map, or asked for)
};

// Points and origin in the scan's (possibly augmented) frame. Training mode samples pillar
// points with rng; inference is deterministic (rng may be null).
ScanInputs compute_scan_inputs(const std::vector<Point>& points, const Eigen::Vector3d& origin,
                               const ModelConfig& config, host::SampleMode mode, Rng* rng,
                               bool want_observability = false);

// The 2D occupancy input (1, H, W): log(1 + count) of the observability counts (H, W).
Tensor<float> observability_input(const Tensor<uint32_t>& observability);

// Concatenates the scans' pillars (cells get their sample index) and stacks the maps.
ModelBatch collate(const std::vector<const ScanInputs*>& scans, const ModelConfig& config);
// The batch of one scan, taking its pillar points and input maps instead of copying them (the
// scan keeps its observability); the same batch as collate({&scan}, config).
ModelBatch collate(ScanInputs&& scan, const ModelConfig& config);

}  // namespace pillarseg
