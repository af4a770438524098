// ScanDataset: the scans of some sequences of a SemanticKITTI root, with everything training
// and evaluation need per scan: network inputs, labels (sparse or dense ground truth through
// the on-disk cache), and the observability mask of Dense Eval. Training samples are augmented
// from their own random stream, Rng::derive(seed, epoch, index), so a sample does not depend
// on which thread builds it or on the order of the others.
#pragma once

#include <filesystem>
#include <memory>
#include <optional>
#include <vector>

#include "engine/data/ground_truth.hpp"
#include "engine/model/run_config.hpp"
#include "engine/pipeline/scan_inputs.hpp"

namespace pillarseg {

struct Sample {
  ScanInputs inputs;
  Tensor<uint8_t> labels;  // (H, W) class ids, 0 = unlabeled
  Tensor<uint8_t> mask;    // (H, W) 1 where observed (observability > 0); empty unless asked for
};

// A training sample for a device pipeline (engine/pipeline/scan_pipeline.hpp): the augmented
// points and sensor origin and the pillars gathered from them on the host (whose seeded subsets
// are one sequence of draws), the maps left to the device.
struct TrainingScan {
  std::vector<Point> points;
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  host::Pillars pillars;
  Tensor<uint8_t> labels;  // (H, W)
};

class ScanDataset {
 public:
  struct Item {
    size_t sequence_slot;  // index into the dataset's sequences
    size_t scan;           // index within the Sequence
  };

  // stride: every stride-th scan; max_per_sequence: 0 = all; input: the run config's input
  // mapping, applied to every scan (and pose) read.
  ScanDataset(const std::filesystem::path& root, const std::vector<int>& sequences, int stride, int max_per_sequence,
              const ModelConfig& model, const ClassTable& classes, GroundTruthKind kind,
              const std::optional<std::filesystem::path>& cache_dir, bool augmented_dense,
              const InputMapping& input = {});

  size_t size() const { return items_.size(); }
  const Item& item(size_t i) const { return items_.at(i); }
  const Sequence& sequence(size_t slot) const { return builders_.at(slot)->sequence(); }
  std::string describe(size_t i) const;  // "08/000123"

  // Augmented (when train.augment) training sample i of `epoch`.
  Sample training_sample(size_t i, uint64_t epoch, const TrainConfig& train) const;
  // The same sample (the same draws, so the same pillars and labels) with its points instead of
  // its network inputs.
  TrainingScan training_scan(size_t i, uint64_t epoch, const TrainConfig& train) const;
  // Unaugmented sample with ground truth of `kind`; with_mask: the observability mask too.
  Sample eval_sample(size_t i, GroundTruthKind kind, bool with_mask) const;
  // The same sample's targets alone (labels, and the mask with with_mask; no network inputs), for
  // a pipeline that prepares the inputs from the scan itself, and the scan.
  Sample eval_targets(size_t i, GroundTruthKind kind, bool with_mask) const;
  Scan scan(size_t i) const;
  // Builds the ground-truth cache of every scan (progress on stderr).
  void build_cache(GroundTruthKind kind) const;

 private:
  // Scan i of `epoch` moved by its augmentation (drawn first from its stream), and its labels; the
  // stream goes on to the pillars' draws.
  struct AugmentedScan {
    Scan scan;
    Rng rng;
    AugmentTransform transform;
    GroundBend bend;
    Eigen::Vector3d origin = Eigen::Vector3d::Zero();
    Tensor<uint8_t> labels;
  };
  AugmentedScan augmented_scan(size_t i, uint64_t epoch, const TrainConfig& train) const;

  ModelConfig model_;
  ClassTable classes_;
  GroundTruthKind kind_;
  std::vector<std::unique_ptr<GroundTruthBuilder>> builders_;
  std::vector<Item> items_;
};

}  // namespace pillarseg
