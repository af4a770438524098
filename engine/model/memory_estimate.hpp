// Sizes of a PillarSegNet checked from its config before anything big is allocated (DESIGN.md
// section 9): the memory a grid and batch size would need, and the counts stored in 32-bit
// indices.
//
// estimate_model_memory() counts, in FP32 (16-bit activations only make it smaller), the memory
// of the backend the model runs on:
//   - parameters: every value and BatchNorm buffer; training adds the gradients and Adam's two
//     moments (x 4 for the trainable values);
//   - activations: the U-Net's feature maps, level l (H / 2^l x W / 2^l cells) holding c_l
//     channels (b 2^l, the widths of DESIGN.md section 2), with the input maps, the outputs
//     (logits, their gradient, the probabilities) and the labels. Evaluation: the largest set
//     alive at once under the lifetime planner (engine/model/graph.hpp), over its phases: the
//     inputs (the canvas, the occupancy and grid-map inputs, with the pillar buffers, which die
//     there); each Down block (its input, pooled map, arg-max, convolution outputs); each Up
//     block (its input, the skip, the concatenation, the first convolution's output), with the
//     skips of the finer levels the decoder has still to read; the head and outputs. Training:
//     every forward tensor the backward reads (pooled maps and their arg-max, each convolution's
//     output and its BatchNorm's, the concatenations, the occupancy stream's, the logits and
//     their gradient), plus the gradients at their peak (the last Up block's concatenation's,
//     split into the canvas's and the upsampled map's, with the coarser levels' outputs' waiting
//     for their Down blocks);
//   - pillars: the pillar buffers, P rows x N points x 10 features plus the cells and the PFN's
//     output (training: its arg-max, gradients and working memory); P = model.max_pillars a
//     sample, or with max_pillars 0 one pillar a cell up to kTypicalScanPoints, with the model's
//     headroom of a quarter; a scan with more pillars is checked again when it is planned;
// (The batch prepared on the host before its upload is small against the activations.)
// It is meant as an upper estimate of what the planner then places: tests/test_memory_budget.cpp
// holds it between 0.95x (the greedy placement may leave small gaps) and 2x of the plan for
// several variants; the plan itself is checked again, exactly, before its block is allocated
// (PillarSegNet::plan), and so are a scan's buffers (ScanPipeline::reserve).
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
  uint64_t activations = 0;
  uint64_t pillars = 0;
  uint64_t total() const;
  // "parameters 65.8 MiB, activations 1.2 GiB, pillar buffers 166.9 MiB".
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
