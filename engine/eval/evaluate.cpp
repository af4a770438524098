#include "engine/eval/evaluate.hpp"

#include "engine/pipeline/dataset.hpp"
#include "engine/util/progress.hpp"

namespace pillarseg {

SegmentationMetrics evaluate(ScanSegmenter& segmenter, const RunConfig& config,
                             const EvalOptions& options) {
  PillarSegNet& net = segmenter.net();
  // Mirrored copies (flips > 1) are the segmenter's: then the CPU, too, runs it on the raw points.
  const bool on_host = segmenter.backend().device() == Device::Cpu && segmenter.flips() == 1;
  const std::vector<int>& sequences =
      options.sequences.empty() ? config.eval.sequences : options.sequences;
  const int stride = options.scan_stride > 0 ? options.scan_stride : config.eval.scan_stride;
  const ClassTable classes = ClassTable::defaults();
  ScanDataset data(options.data_root, sequences, stride, 0, config.model, classes, options.mode,
                   options.cache_dir, false, config.input);
  const bool dense = options.mode == GroundTruthKind::dense;
  PS_CHECK(options.shards >= 1 && options.shard >= 0 && options.shard < options.shards,
           "evaluate: shard {} of {} does not exist", options.shard, options.shards);
  SegmentationMetrics metrics;
  const auto shards = static_cast<size_t>(options.shards);
  const size_t scans = (data.size() + shards - 1 - static_cast<size_t>(options.shard)) / shards;
  Progress progress(dense ? "dense eval" : "sparse eval", static_cast<int64_t>(scans), "scans");
  Tensor<uint8_t> predicted({config.model.grid.height(), config.model.grid.width()});
  for (size_t i = static_cast<size_t>(options.shard), done = 0; i < data.size(); i += shards) {
    Sample s;
    if (on_host) {
      s = data.eval_sample(i, options.mode, dense);
      net.forward(collate(std::move(s.inputs), config.model), /*training=*/false);
      predicted = net.predict_labels();
      predicted.reshape(s.labels.shape());
    } else {
      s = data.eval_targets(i, options.mode, dense);
      segmenter.segment_mapped(data.scan(i).points, predicted.data());  // mapped by the data set
    }
    metrics.add(s.labels, predicted, dense ? &s.mask : nullptr);
    if (options.progress) progress.update(static_cast<int64_t>(++done));
  }
  if (options.progress) progress.finish();
  return metrics;
}

std::string eval_mode_label(GroundTruthKind train, GroundTruthKind eval) {
  return std::string(train == GroundTruthKind::dense ? "Dense Train" : "Sparse Train") + " / " +
         (eval == GroundTruthKind::dense ? "Dense Eval" : "Sparse Eval");
}

std::string method_label(const ModelConfig& model) {
  if (!model.pillar_input && model.grid_map_input && model.occupancy == OccupancyInput::None)
    return "Grid map (Bieder et al.)";
  std::string s = model.pillar_input ? "Pillar" : "";
  const auto join = [&](const std::string& part) { s += (s.empty() ? "" : " + ") + part; };
  if (model.occupancy == OccupancyInput::Observability2D) join("2D Occupancy");
  if (model.occupancy == OccupancyInput::Occupancy3D) join("3D Occupancy");
  if (model.grid_map_input) join("Grid map");
  return s;
}

}  // namespace pillarseg
