// Checkpoints are safetensors files. The model's tensors carry their PyTorch state_dict names
// (DESIGN.md section 2), so a PyTorch model with the authors' module names loads them with
// load_state_dict, and we load theirs. A training checkpoint adds the Adam moments
// (optimizer.exp_avg / optimizer.exp_avg_sq, flat, in parameter order) and, in the metadata,
// the run's YAML config, the epoch and the optimiser step; everything else a resumed run needs
// (sample order, augmentation) derives from the seed, epoch and sample index.
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <vector>

#include "engine/model/pillarsegnet.hpp"
#include "engine/model/run_config.hpp"
#include "weights_io/safetensors.hpp"

namespace pillarseg {

struct TrainState {
  int64_t epoch = 0;  // epochs completed
  int64_t step = 0;   // optimiser steps completed
  // Validation while training: the best mIoU so far (negative: none yet) and its epoch.
  double best_miou = -1;
  int64_t best_epoch = 0;
  // train.average_epochs: the sum of the trainable values at the end of each epoch of the
  // averaging window so far (empty outside it); kept with the optimizer state.
  std::vector<float> average_sum;
};
inline constexpr const char* kAverageSumName = "optimizer.average_sum";

// Writes atomically (temporary file, then rename).
void save_checkpoint(const std::filesystem::path& path, const PillarSegNet& net, const RunConfig& config,
                     const TrainState& state, bool with_optimizer);

struct Checkpoint {
  weights::SafeTensors file;
  std::optional<RunConfig> config;  // absent in a weights-only file (e.g. exported from PyTorch)
  TrainState state;
  bool has_optimizer = false;
};
Checkpoint read_checkpoint(const std::filesystem::path& path);

// Loads every model tensor by name; a missing, extra or misshaped tensor is an error that
// names them all. with_optimizer: the Adam moments too (required then).
void load_weights(const Checkpoint& checkpoint, PillarSegNet& net, bool with_optimizer);

// The run config of --config when given (which wins), else the checkpoint's; a weights-only file
// without --config gets the architecture of its tensor shapes (engine/model/architecture.hpp) on
// the paper's grid, and the default training and evaluation settings.
RunConfig config_for(const Checkpoint& checkpoint, const std::filesystem::path& config_override);

}  // namespace pillarseg
