#include "engine/pipeline/dataset.hpp"

#include <fmt/format.h>

#include "core/error.hpp"
#include "host/rasterize_labels.hpp"

namespace pillarseg {

namespace fs = std::filesystem;

ScanDataset::ScanDataset(const fs::path& root, const std::vector<int>& sequences, int stride, int max_per_sequence,
                         const ModelConfig& model, const ClassTable& classes, GroundTruthKind kind,
                         const std::optional<fs::path>& cache_dir, bool augmented_dense,
                         const InputMapping& input)
    : model_(model), classes_(classes), kind_(kind) {
  PS_CHECK(stride >= 1, "scan stride must be >= 1, got {}", stride);
  const std::vector<int> present = list_sequences(root);
  GroundTruthSettings settings;
  settings.grid = model.grid;
  // Dense training with augmentation re-rasterises each scan's aggregated point set after
  // moving it: caching those sets avoids reading 40 scans per sample every epoch.
  settings.cache_dense_points = augmented_dense;
  const fs::path cache_root = cache_dir ? *cache_dir : default_cache_dir(root);
  for (int id : sequences) {
    PS_CHECK(std::find(present.begin(), present.end(), id) != present.end(),
             "sequence {} not found under {}/sequences (present: {})", sequence_name(id), root.string(),
             fmt::join(present, ", "));
    auto builder = std::make_unique<GroundTruthBuilder>(Sequence(root, id, input), classes, settings, Cache(cache_root));
    const Sequence& seq = builder->sequence();
    size_t taken = 0;
    for (size_t i = 0; i < seq.size(); i += static_cast<size_t>(stride)) {
      if (max_per_sequence > 0 && taken >= static_cast<size_t>(max_per_sequence)) break;
      PS_CHECK(seq.has_labels(i), "{}: no labels for this scan (training and evaluation need labels)",
               seq.label_path(i).string());
      items_.push_back({builders_.size(), i});
      ++taken;
    }
    builders_.push_back(std::move(builder));
  }
  PS_CHECK(!items_.empty(), "no scans in sequences {} under {}", fmt::join(sequences, ", "), root.string());
}

std::string ScanDataset::describe(size_t i) const {
  const Item& it = item(i);
  const Sequence& seq = sequence(it.sequence_slot);
  return fmt::format("{}/{:06}", sequence_name(seq.id()), seq.frame(it.scan));
}

namespace {

// The labels of an augmented scan: its sparse ground truth, or the dense one of its aggregated
// neighbours moved by the same transform and ground bend.
Tensor<uint8_t> training_labels(const Scan& scan, const GroundTruthBuilder& builder, size_t index,
                                GroundTruthKind kind, const AugmentTransform& transform,
                                const GroundBend& bend, const ClassTable& classes, const GridSpec& grid) {
  if (kind == GroundTruthKind::sparse) return rasterize_labels(scan.points, scan.labels, classes, grid);
  if (transform.is_identity() && bend.is_identity()) return builder.map(index, GroundTruthKind::dense);
  LabelledPoints aggregated = builder.dense_points(index);
  aggregated.transform(transform.as_matrix());
  bend.apply(aggregated.points);
  return rasterize_classes(aggregated.points, aggregated.classes, classes, grid);
}

}  // namespace

ScanDataset::AugmentedScan ScanDataset::augmented_scan(size_t i, uint64_t epoch, const TrainConfig& train) const {
  const Item& it = item(i);
  const GroundTruthBuilder& builder = *builders_[it.sequence_slot];
  AugmentedScan a{builder.sequence().load(it.scan), Rng::derive(train.seed, epoch, i), {}, {}, Eigen::Vector3d::Zero(), {}};
  if (train.augment) a.transform = sample_augmentation(train.augmentation, a.rng);
  if (!a.transform.is_identity()) a.transform.apply(a.scan.points);
  if (train.augment) a.bend = sample_ground_bend(train.augmentation, a.rng);
  a.bend.apply(a.scan.points);
  if (train.augment && train.augmentation.randomises_points())
    sample_randomisation(train.augmentation, a.rng).apply(a.scan.points, a.scan.labels);
  a.origin = a.transform.apply(Eigen::Vector3d::Zero());
  a.origin.z() += a.bend.offset(a.origin.x(), a.origin.y());
  a.labels = training_labels(a.scan, builder, it.scan, kind_, a.transform, a.bend, classes_, model_.grid);
  return a;
}

Sample ScanDataset::training_sample(size_t i, uint64_t epoch, const TrainConfig& train) const {
  AugmentedScan a = augmented_scan(i, epoch, train);
  Sample s;
  s.inputs = compute_scan_inputs(a.scan.points, a.origin, model_, host::SampleMode::Training, &a.rng);
  s.labels = std::move(a.labels);
  return s;
}

TrainingScan ScanDataset::training_scan(size_t i, uint64_t epoch, const TrainConfig& train) const {
  AugmentedScan a = augmented_scan(i, epoch, train);
  TrainingScan s;
  s.origin = a.origin;
  if (model_.pillar_input) {
    const host::PillarConfig pc{model_.max_points_per_pillar, model_.max_pillars};
    s.pillars = host::pillar_gather(a.scan.points, model_.grid, pc, host::SampleMode::Training, &a.rng);
  }
  s.labels = std::move(a.labels);
  s.points = std::move(a.scan.points);
  return s;
}

Sample ScanDataset::eval_sample(size_t i, GroundTruthKind kind, bool with_mask) const {
  const Item& it = item(i);
  const GroundTruthBuilder& builder = *builders_[it.sequence_slot];
  const Scan scan = builder.sequence().load(it.scan);
  // Unaugmented scans: the ray-walk maps come from the cache (the grid-map layers need the
  // per-cell detection and transmission counts and are computed).
  ModelConfig direct = model_;
  direct.occupancy = OccupancyInput::None;
  Sample s;
  s.inputs = compute_scan_inputs(scan.points, Eigen::Vector3d::Zero(), direct, host::SampleMode::Inference, nullptr);
  if (model_.occupancy == OccupancyInput::Occupancy3D) s.inputs.occupancy = builder.occupancy(it.scan);
  if (model_.occupancy == OccupancyInput::Observability2D || with_mask) {
    s.inputs.observability = builder.observability(it.scan);
    if (model_.occupancy == OccupancyInput::Observability2D) s.inputs.occupancy = observability_input(s.inputs.observability);
  }
  s.labels = builder.map(it.scan, kind);
  if (with_mask) {
    s.mask = Tensor<uint8_t>(s.inputs.observability.shape());
    for (int64_t c = 0; c < s.mask.numel(); ++c) s.mask[c] = s.inputs.observability[c] > 0;
  }
  return s;
}

Sample ScanDataset::eval_targets(size_t i, GroundTruthKind kind, bool with_mask) const {
  const Item& it = item(i);
  const GroundTruthBuilder& builder = *builders_[it.sequence_slot];
  Sample s;
  s.labels = builder.map(it.scan, kind);
  if (with_mask) {
    const Tensor<uint32_t> observability = builder.observability(it.scan);
    s.mask = Tensor<uint8_t>(observability.shape());
    for (int64_t c = 0; c < s.mask.numel(); ++c) s.mask[c] = observability[c] > 0;
  }
  return s;
}

Scan ScanDataset::scan(size_t i) const {
  const Item& it = item(i);
  return builders_[it.sequence_slot]->sequence().load(it.scan);
}

void ScanDataset::build_cache(GroundTruthKind kind) const {
  for (const auto& builder : builders_) builder->build_all(kind, true);
}

}  // namespace pillarseg
