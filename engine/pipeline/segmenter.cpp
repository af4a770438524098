#include "engine/pipeline/segmenter.hpp"

#include <spdlog/spdlog.h>

#include <string>

#include "core/error.hpp"
#include "core/parallel.hpp"
#include "engine/model/checkpoint.hpp"

namespace pillarseg {

ScanSegmenter::ScanSegmenter(const ModelConfig& model, std::unique_ptr<Backend> backend,
                             const SegmenterOptions& options, uint64_t seed)
    : model_(model),
      options_(options),
      backend_(std::move(backend)),
      net_(std::make_unique<PillarSegNet>(model, *backend_, seed)),
      pipeline_(model, *backend_, options.mask_unobserved) {
  check_flips(options.flips, model.grid, "flips");
  if (options.precision == Precision::F32) return;
  std::string why;
  if (backend_->supports_precision(options.precision, &why)) {
    net_->set_precision(options.precision);
  } else {
    spdlog::warn("--precision {}: {}; running fp32", precision_name(options.precision), why);
  }
}

void ScanSegmenter::queue_predictions(bool probabilities) {
  net_->queue_predictions(probabilities);
  if (!options_.mask_unobserved) return;
  LRef labels = net_->predicted();
  Ref probs = net_->probs();
  backend_->mask_unobserved(pipeline_.transmissions(), pipeline_.detections(), labels,
                            probabilities ? &probs : nullptr);
}

void ScanSegmenter::queue_recordable(bool probabilities) {
  pipeline_.pad_points();
  const Ref points = pipeline_.point_buffer();
  const int64_t rows = pipeline_.gather_pillars(points);
  const PillarSegNet::Inputs inputs = net_->prepare(1, rows, /*training=*/false);
  pipeline_.fill_pillars(points, rows, 0, 0, inputs);
  pipeline_.fill_maps(points, Eigen::Vector3d::Zero(), 0, inputs);
  run_network();
  queue_predictions(probabilities);
}

void ScanSegmenter::run_network() {
  // Unset again however run() ends: the net's other callers give it inputs without a P'.
  struct Unset {
    PillarSegNet& net;
    ~Unset() { net.set_live_pillar_rows(IRef{}); }
  } unset{*net_};
  net_->set_live_pillar_rows(pipeline_.live_pillar_rows());
  net_->run(/*training=*/false);
}

void ScanSegmenter::queue_direct(const Ref& points, bool probabilities) {
  Backend& be = *backend_;
  double last = time_stages_ ? be.clock_ms() : 0.0;
  const auto lap = [&](double& stage) {
    if (!time_stages_) return;
    const double now = be.clock_ms();
    stage = now - last;
    last = now;
  };
  const int64_t rows = pipeline_.gather_pillars(points);
  const PillarSegNet::Inputs inputs = net_->prepare(1, rows, /*training=*/false);
  pipeline_.fill_pillars(points, rows, 0, 0, inputs);
  lap(times_.pillars);
  pipeline_.fill_maps(points, Eigen::Vector3d::Zero(), 0, inputs);
  lap(times_.maps);
  net_->set_stage_timing(time_stages_);
  run_network();
  net_->set_stage_timing(false);
  if (time_stages_) {
    const PillarSegNet::StageTimes& net = net_->stage_times();
    times_.pfn = net.pfn, times_.scatter = net.scatter, times_.occupancy = net.occupancy;
    times_.unet = net.unet, times_.head = net.head;
    last = be.clock_ms();
  }
  queue_predictions(probabilities);
  lap(times_.predict);
}

void ScanSegmenter::segment(std::span<const Point> points, uint8_t* labels, float* probabilities) {
  if (input_.is_identity()) return segment_mapped(points, labels, probabilities);
  mapped_.assign(points.begin(), points.end());
  input_.apply(mapped_);
  segment_mapped(mapped_, labels, probabilities);
}

ScanSegmenter::StageTimes& ScanSegmenter::StageTimes::operator+=(const StageTimes& o) {
  upload += o.upload, pillars += o.pillars, maps += o.maps, pfn += o.pfn, scatter += o.scatter;
  occupancy += o.occupancy, unet += o.unet, head += o.head, predict += o.predict, download += o.download;
  return *this;
}

void ScanSegmenter::segment_mapped(std::span<const Point> points, uint8_t* labels, float* probabilities) {
  PS_CHECK(labels != nullptr, "segment: labels must point to H x W = {} bytes", model_.grid.cells());
  if (options_.flips == 1) return segment_once(points, labels, probabilities);
  segment_flipped(points, labels, probabilities);
}

void ScanSegmenter::segment_flipped(std::span<const Point> points, uint8_t* labels, float* probabilities) {
  Backend& be = *backend_;
  be.make_current();
  const ScopedThreads threads(options_.threads);
  const int64_t width = model_.grid.width(), height = model_.grid.height();
  if (!flip_arena_) {
    // The running sum (1, K, H, W) and its arg-max (1, H, W), in the backend's memory: on a GPU
    // only the result comes down.
    flip_arena_ = std::make_unique<Arena>(be);
    const Shape sum_shape{1, model_.num_classes, height, width}, label_shape{1, height, width};
    flip_arena_->begin_measure();
    (void)flip_arena_->take<float>(sum_shape);
    (void)flip_arena_->take<uint8_t>(label_shape);
    flip_arena_->reserve(flip_arena_->used());
    flip_arena_->reset();
    flip_sum_ = flip_arena_->take<float>(sum_shape);
    flip_labels_ = flip_arena_->take<uint8_t>(label_shape);
  }
  be.fill_zero(flip_sum_.data, flip_sum_.bytes());
  StageTimes total;
  // Copy f mirrors y where bit 0 is set and x where bit 1 is: the scan, y, x, both. A point at
  // y lands in row height - 1 - iy of the mirrored copy (the grid is symmetric: check_flips), so
  // cell (iy, ix) of the scan reads the copy's cell (height - 1 - iy, ix): mirror_add.
  for (int f = 0; f < options_.flips; ++f) {
    const bool mirror_y = (f & 1) != 0, mirror_x = (f & 2) != 0;
    if (f > 0) {
      mirrored_.assign(points.begin(), points.end());
      for (Point& p : mirrored_) {
        if (mirror_y) p.y = -p.y;
        if (mirror_x) p.x = -p.x;
      }
    }
    queue_pass(f > 0 ? std::span<const Point>(mirrored_) : points, /*probabilities=*/true);
    const double start = time_stages_ ? be.clock_ms() : 0.0;
    be.mirror_add(net_->probs(), mirror_y, mirror_x, flip_sum_);
    if (time_stages_) times_.predict += be.clock_ms() - start;
    total += times_;
  }
  // The arg-max of the sum is the mean's (the first class wins a tie, as the backends' arg-max);
  // a cell masked as unobserved in every copy has probabilities 0 in all of them: class 0.
  const double start = time_stages_ ? be.clock_ms() : 0.0;
  be.argmax_positive(flip_sum_, flip_labels_);
  if (probabilities != nullptr) be.scale(flip_sum_, 1.0f / static_cast<float>(options_.flips));
  if (time_stages_) total.predict += be.clock_ms() - start;
  times_ = total;
  download(flip_labels_.data, flip_sum_.data, labels, probabilities);
}

void ScanSegmenter::segment_once(std::span<const Point> points, uint8_t* labels, float* probabilities) {
  const ScopedThreads threads(options_.threads);
  queue_pass(points, probabilities != nullptr);
  download(net_->predicted().data, net_->probs().data, labels, probabilities);
}

void ScanSegmenter::download(const uint8_t* device_labels, const float* device_probabilities, uint8_t* labels,
                             float* probabilities) {
  Backend& be = *backend_;
  const double start = time_stages_ ? be.clock_ms() : 0.0;
  const int64_t cells = model_.grid.cells();
  be.download(labels, device_labels, static_cast<size_t>(cells));
  if (probabilities != nullptr)
    be.download(probabilities, device_probabilities,
                static_cast<size_t>(cells) * static_cast<size_t>(model_.num_classes) * sizeof(float));
  if (time_stages_) times_.download = be.clock_ms() - start;
}

void ScanSegmenter::queue_pass(std::span<const Point> points, bool with_probabilities) {
  Backend& be = *backend_;
  be.make_current();
  times_ = StageTimes{};
  double last = time_stages_ ? be.clock_ms() : 0.0;
  const Ref loaded = pipeline_.load_points(points);
  if (time_stages_) {
    const double now = be.clock_ms();
    times_.upload = now - last;
  }

  // Recorded where the backend records, except while timing stages or while a calibration
  // observes the convolutions' inputs (it downloads them as the forward runs).
  if (be.supports_capture() && !time_stages_ && !net_->observing_conv_inputs()) {
    Recording& r = recordings_[with_probabilities ? 1 : 0];
    const bool current = r.graph && r.graph->valid() && r.buffer_generation == pipeline_.buffer_generation() &&
                         r.model_generation == net_->memory_generation();
    if (current) {
      net_->refresh_prepared_weights();  // the recording holds no weight preparation
      r.graph->replay();
    } else {
      // Once uncaptured: every buffer and workspace grows to this capacity (and this scan's
      // result is computed); then the same work is recorded, without running it.
      r.graph.reset();
      queue_recordable(with_probabilities);
      r.graph = be.capture([&] { queue_recordable(with_probabilities); });
      r.buffer_generation = pipeline_.buffer_generation();
      r.model_generation = net_->memory_generation();
    }
  } else {
    queue_direct(loaded, with_probabilities);
  }
}

std::unique_ptr<ScanSegmenter> open_segmenter(const Checkpoint& checkpoint, const RunConfig& config,
                                              const std::filesystem::path& weights,
                                              const SegmenterOptions& options) {
  auto segmenter = std::make_unique<ScanSegmenter>(config.model, make_backend(options.device, options.backend),
                                                   options);
  load_weights(checkpoint, segmenter->net(), /*with_optimizer=*/false);
  PS_CHECK(options.precision != Precision::I8 || !segmenter->net().int8_inputs().empty(),
           "{}: precision int8: no input scale for the convolutions (the weights are not calibrated: pillarseg "
           "calibrate writes the scales into a checkpoint)",
           weights.string());
  segmenter->set_input_mapping(config.input);
  return segmenter;
}

std::unique_ptr<ScanSegmenter> open_segmenter(const std::filesystem::path& weights,
                                              const std::filesystem::path& config_path,
                                              const SegmenterOptions& options) {
  const Checkpoint checkpoint = read_checkpoint(weights);
  return open_segmenter(checkpoint, config_for(checkpoint, config_path), weights, options);
}

}  // namespace pillarseg
