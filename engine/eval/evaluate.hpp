// Evaluation (DESIGN.md section 3): run a trained model over a split and accumulate the
// confusion matrix. Sparse Eval scores against sparse ground truth; Dense Eval against dense
// ground truth, ignoring cells the scan did not observe (observability 0).
#pragma once

#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "engine/data/ground_truth.hpp"
#include "engine/eval/metrics.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "engine/model/run_config.hpp"
#include "engine/pipeline/segmenter.hpp"

namespace pillarseg {

struct EvalOptions {
  std::filesystem::path data_root;
  GroundTruthKind mode = GroundTruthKind::sparse;
  std::vector<int> sequences;  // empty: the config's eval.sequences
  int scan_stride = 0;         // 0: the config's eval.scan_stride
  std::optional<std::filesystem::path> cache_dir;
  bool progress = true;
  // Scans i of the split with i % shards == shard only (validation on the replicas of a
  // data-parallel run, whose confusion matrices add up to the whole split's).
  int shard = 0, shards = 1;
};

// The segmenter's model over the split. On the CPU backend the inputs come from the host pipeline
// with the cached maps (as training reads them); on a CUDA backend, and with the segmenter's
// mirrored copies (flips > 1) on any, each scan's raw points go through the segmenter's pipeline
// (ScanSegmenter::segment_mapped).
SegmentationMetrics evaluate(ScanSegmenter& segmenter, const RunConfig& config, const EvalOptions& options);

// Table I row labels: "Sparse Train / Dense Eval" and "Pillar + 2D Occupancy".
std::string eval_mode_label(GroundTruthKind train, GroundTruthKind eval);
std::string method_label(const ModelConfig& model);

}  // namespace pillarseg
