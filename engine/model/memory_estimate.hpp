// Sizes of a PillarSegNet checked from its config before anything big is allocated (DESIGN.md
// section 9): the memory a grid and batch size would need, and the counts stored in 32-bit
// indices.
//
// estimate_model_memory() is what the model would hold, derived from the model itself (DESIGN.md
// section 7: derived, never restated): the parameters as PillarSegNet declares them (values and
// BatchNorm buffers; training adds the gradients and Adam's two moments, x 4 for the trainable
// values), and the block the lifetime planner places for the FP32 op graph of that batch and mode
// (engine/model/model_graph.hpp), its pillar buffers planned for model.max_pillars a sample, or
// with max_pillars 0 one pillar a cell up to kTypicalScanPoints, with the model's headroom (a scan
// with more pillars is checked again when it is planned). The plan itself is checked again,
// exactly, before its block is allocated (PillarSegNet::plan), and so are a scan's buffers
// (ScanPipeline::reserve); the batch prepared on the host before its upload is small against the
// activations.
#pragma once

#include <cstdint>
#include <string>

#include "core/memory_budget.hpp"
#include "engine/model/config.hpp"

namespace pillarseg {

// With model.max_pillars 0, the pillars a sample is assumed to have at most, for the estimate: a
// 64-beam sweep has about 120k points, so no more non-empty pillars.
inline constexpr int64_t kTypicalScanPoints = 131072;

struct ModelMemoryEstimate {
  uint64_t parameters = 0;
  uint64_t activations = 0;  // the planned block, the pillar buffers in it
  uint64_t pillars = 0;      // of the activations: the pillar buffers (at their largest)
  uint64_t total() const;    // parameters + activations
  // "parameters 65.8 MiB, activations 1.2 GiB (pillar buffers 166.9 MiB of them)".
  std::string breakdown() const;
};

// Throws pillarseg::Error when a size overflows 64-bit arithmetic, naming it.
ModelMemoryEstimate estimate_model_memory(const ModelConfig& config, int batch, bool training);

// Throws pillarseg::Error "evaluation of a 40000 x 40000 grid (batch 1) would need 1.4 TiB, more
// than the 21.9 GiB of memory available (...); the estimate: parameters ..., activations ..."
// when the estimate exceeds the budget.
void check_model_memory(const ModelConfig& config, int batch, bool training,
                        const MemoryBudget& budget);

// The counts PillarSegNet and its ops store in int32, for `batch` samples: the cells of a sample
// (flat cell indices iy W + ix, the arg-max of a pooled map), the pillar rows of a batch (pillar
// ids: model.max_pillars a sample, or up to one a cell with max_pillars 0) and, with max_pillars
// set, the PFN's P x N point rows. Throws pillarseg::Error naming the count and the limit, e.g.
// "grid of 70000 x 70000 cells x batch 2 = 9800000000 overflows the 32-bit pillar indices (at
// most 2147483647)". The grid's axes themselves are checked by ModelConfig::validate().
void check_index_limits(const ModelConfig& config, int batch);

}  // namespace pillarseg
