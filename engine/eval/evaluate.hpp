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
#include "engine/train/run_config.hpp"

namespace pillarseg {

struct EvalOptions {
  std::filesystem::path data_root;
  GroundTruthKind mode = GroundTruthKind::sparse;
  std::vector<int> sequences;  // empty: the config's eval.sequences
  int scan_stride = 0;         // 0: the config's eval.scan_stride
  std::optional<std::filesystem::path> cache_dir;
  bool progress = true;
};

// One scan through the network (eval mode): class ids (H, W), optionally the softmax
// probabilities (12, H, W) and the observability counts (H, W).
struct Prediction {
  Tensor<uint8_t> labels;
  Tensor<float> probabilities;
  Tensor<uint32_t> observability;
};
Prediction predict_scan(PillarSegNet& net, const ModelConfig& model, const std::vector<Point>& points,
                        bool with_probabilities, bool with_observability);

SegmentationMetrics evaluate(PillarSegNet& net, const RunConfig& config, const EvalOptions& options);

// Table I row labels: "Sparse Train / Dense Eval" and "Pillar + 2D Occupancy".
std::string eval_mode_label(GroundTruthKind train, GroundTruthKind eval);
std::string method_label(const ModelConfig& model);

}  // namespace pillarseg
