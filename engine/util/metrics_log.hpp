// A training run's log, RUN_DIR/metrics.jsonl (written by engine/train/trainer.cpp: one JSON
// object a line), read back for `pillarseg plot`: its step, epoch and eval lines, in file order.
// Lines of another "type" are skipped (a newer trainer's); a line that is not JSON, or a step,
// epoch or eval line missing a field or holding the wrong kind of value, fails naming file:line.
// Fields later trainers added (the epoch's data_wait_s, the eval's confusion) may be absent.
#pragma once

#include <array>
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "core/classes.hpp"

namespace pillarseg {

// {"type": "step", ...}: one optimiser step.
struct StepRecord {
  int64_t epoch = 0, step = 0;
  double loss = 0, lr = 0, beta1 = 0, grad_norm = 0, elapsed_s = 0;
};

// {"type": "epoch", ...}: the end of an epoch (mean loss over its steps).
struct EpochRecord {
  int64_t epoch = 0, step = 0;
  double mean_loss = 0;
  double data_wait_s = 0;  // NaN in logs written before the trainer logged it
  std::string checkpoint;
};

// {"type": "eval", ...}: validation after an epoch. NaN where the log says null (a class, or
// every class, with an empty union).
struct EvalRecord {
  int64_t epoch = 0, step = 0, labelled_cells = 0, best_epoch = 0;
  std::string mode;  // "sparse" or "dense"
  double miou = 0;
  // Class ids 1..12 in ClassTable order: the names the log gives and their IoU.
  std::array<std::string, kNumClasses> class_names;
  std::array<double, kNumClasses> iou{};
  // (12, 12), row the true class, column the predicted one; empty in logs written before the
  // trainer logged it.
  std::vector<std::array<int64_t, kNumClasses>> confusion;
};

struct TrainingLog {
  std::vector<StepRecord> steps;
  std::vector<EpochRecord> epochs;
  std::vector<EvalRecord> evals;
};

// Throws pillarseg::Error naming the file (missing, unreadable) or file:line (malformed).
TrainingLog read_training_log(const std::filesystem::path& path);

}  // namespace pillarseg
