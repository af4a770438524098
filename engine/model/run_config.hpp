// RunConfig: one YAML file (configs/*.yaml) with the grid, the model, training and
// evaluation settings (configs/README.md lists every key). Unknown keys are errors, so a typo
// does not silently train the wrong model. The file's text travels in every checkpoint.
#pragma once

#include <array>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "core/classes.hpp"
#include "engine/data/augment.hpp"
#include "engine/data/input_mapping.hpp"
#include "engine/data/ground_truth.hpp"
#include "engine/backend/backend.hpp"
#include "engine/model/config.hpp"

namespace pillarseg {

struct TrainConfig {
  GroundTruthKind ground_truth = GroundTruthKind::sparse;
  LossKind loss = LossKind::CrossEntropy;
  int epochs = 30;
  int batch_size = 2;
  uint64_t seed = 0;
  // Adam with decoupled weight decay; OpenPCDet's adam_onecycle or a constant rate.
  double lr = 1e-3, weight_decay = 0.01, beta2 = 0.99, eps = 1e-8;
  bool onecycle = true;
  double div_factor = 10, pct_start = 0.4, momentum_max = 0.95, momentum_min = 0.85;
  double grad_clip = 10;  // 0: off
  bool augment = true;
  AugmentConfig augmentation;
  std::array<float, kNumClassIds> coefficients{};  // per class id; filled by the loader
  std::vector<int> sequences = {0, 1, 2, 3, 4, 5, 6, 7, 9, 10};
  int max_scans_per_sequence = 0;  // 0: all
  int scan_stride = 1;
  // Precise BatchNorm: after each epoch, the running statistics are recomputed as the average
  // over this many unaugmented training batches under the final weights (0: off, keep the
  // momentum averages). Short runs need it: the PFN's momentum of 0.01 still remembers weights
  // from hundreds of steps before.
  int precise_bn_batches = 0;
  // Weight averaging (stochastic weight averaging, Izmailov et al. 2018): the weights at the
  // end of each of the last this many epochs are summed, and after the last epoch the model
  // takes their mean, whose BatchNorm statistics precise BatchNorm then estimates (it must be
  // on). 0: off, the model is the last epoch's weights.
  int average_epochs = 0;
  // Threads preparing samples ahead of the step into a bounded queue (engine/train/prefetcher.hpp);
  // 0: each batch is prepared when the step needs it. The results do not depend on it.
  int workers = 0;
  // Data-parallel training: the gradients are summed over the replicas in buckets of at least
  // this many MiB, each begun as soon as the backward has finished it, so that the sums overlap
  // the rest of the backward (PyTorch DDP's bucket_cap_mb). 0: one sum after the backward. The
  // results do not depend on it.
  double gradient_bucket_mb = 4;
};

struct EvalConfig {
  std::vector<int> sequences = {8};
  int scan_stride = 1;
  // Validation while training: every this many epochs (and after the last), the evaluation of
  // these sequences in `mode` (default: the training ground truth's), logged, and the best mIoU's
  // weights kept in RUN_DIR/best.safetensors. 0: off.
  int every_epochs = 0;
  std::optional<GroundTruthKind> mode;
  // Test-time flips of `pillarseg eval` and of the validation while training: the softmax
  // averaged over 1, 2 or 4 mirrored copies of each scan (SegmenterOptions::flips; flips times
  // the work). infer, render, bench and the library run one pass unless asked (--flips).
  int flips = 1;
};

struct RunConfig {
  ModelConfig model;
  TrainConfig train;
  EvalConfig eval;
  // The `input:` section: the data's sensor into the model's frame and scale, applied to every
  // scan read for training, evaluation and inference (engine/data/input_mapping.hpp).
  InputMapping input;
  std::string text;    // the YAML text it was read from
  std::string source;  // file name, for messages
};

RunConfig load_run_config(const std::filesystem::path& path);
RunConfig parse_run_config(const std::string& yaml_text, const std::string& source);
// The paper's loss coefficients: vehicle 2 (sparse) or 5 (dense); person, two-wheel, rider 8;
// others 1; unlabeled 0.
std::array<float, kNumClassIds> default_coefficients(GroundTruthKind kind);

}  // namespace pillarseg
