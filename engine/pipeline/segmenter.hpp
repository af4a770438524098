// ScanSegmenter: one sweep's points -> the label map (and the probabilities), the whole pipeline
// on one backend (DESIGN.md section 6): what `pillarseg infer`, eval, render and bench run, and
// what the library's C API wraps.
//
// The steady state on a backend that records graphs (CUDA): the points go up through pinned
// staging (16 bytes a point) with their count, one recorded graph runs everything after the
// upload (NaN padding to the recorded point capacity, the pillar gather, decoration, ray walks and
// input maps, the network, the arg-max, the masking of unobserved cells, and the softmax only when
// the probabilities are asked for), and the label map comes down (H x W bytes); nothing is
// allocated and nothing waits but the final download. The first scan, and a scan with more points
// than the capacity, runs once without the graph (growing every buffer to the new capacity, and
// giving this scan's result) and then records. On the CPU backend the same ops run directly on
// the caller's points, for exactly the scan's pillars.
#pragma once

#include <array>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "core/point.hpp"
#include "engine/backend/backend.hpp"
#include "engine/data/input_mapping.hpp"
#include "engine/model/config.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "engine/pipeline/scan_pipeline.hpp"

namespace pillarseg {

struct Checkpoint;  // engine/model/checkpoint.hpp
struct RunConfig;   // engine/model/run_config.hpp

struct SegmenterOptions {
  std::string device = "cpu";  // cpu, cuda or emu (make_backend)
  BackendOptions backend;      // the CUDA backends' convolution and device
  bool mask_unobserved = false;  // cells no ray observed: class 0, probabilities 0
  int threads = 0;               // CPU threads of this segmenter's work, 0: the process's setting
  // The evaluation convolutions' arithmetic; a backend without it (the CPU) says so in one
  // warning line and runs FP32 (precision() tells which runs).
  Precision precision = Precision::F32;
  // Test-time augmentation: the softmax averaged over this many mirrored copies of the scan, the
  // label map its arg-max: 1 the scan alone; 2 and its left-right mirror (y -> -y); 4 and the
  // front-back mirror (x -> -x) and both. Each copy is a whole pass (flips times the work); the
  // mirrors need a grid symmetric about the sensor (check_flips). Training's flip augmentation
  // shows the network both sides, so the copies are in its domain: the mean is an ensemble of
  // four views (docs/simulator.md, experiment 44).
  int flips = 1;
};

class ScanSegmenter {
 public:
  ScanSegmenter(const ModelConfig& model, std::unique_ptr<Backend> backend,
                const SegmenterOptions& options = {}, uint64_t seed = 0);
  ScanSegmenter(const ScanSegmenter&) = delete;
  ScanSegmenter& operator=(const ScanSegmenter&) = delete;

  const ModelConfig& model() const { return model_; }
  Backend& backend() { return *backend_; }
  PillarSegNet& net() { return *net_; }
  const SegmenterOptions& options() const { return options_; }

  // The sensor's points into the model's frame and scale (engine/data/input_mapping.hpp), applied
  // by segment() to a copy of the points; the identity (the default) passes them as given.
  void set_input_mapping(const InputMapping& input) { input_ = input; }
  const InputMapping& input_mapping() const { return input_; }

  // points: the sweep in the sensor frame (one with a NaN or infinite value is ignored), mapped by
  // input_mapping() first. labels: H x W class ids (row iy, column ix); probabilities: 12 x H x W
  // softmax values, or null.
  void segment(std::span<const Point> points, uint8_t* labels, float* probabilities = nullptr);
  // The same for points already in the model's frame and scale (a data set's mapped scans).
  void segment_mapped(std::span<const Point> points, uint8_t* labels, float* probabilities = nullptr);
  int flips() const { return options_.flips; }

  // Stage timing (for pillarseg bench): each segment() then runs without the graph and reads the
  // backend's clock (CUDA events) between stages, in ms.
  struct StageTimes {
    double upload = 0, pillars = 0, maps = 0, pfn = 0, scatter = 0, occupancy = 0, unet = 0,
           head = 0, predict = 0, download = 0;
    StageTimes& operator+=(const StageTimes& o);
  };
  void set_stage_timing(bool on) { time_stages_ = on; }
  const StageTimes& stage_times() const { return times_; }

 private:
  // One pass over the points as given (segment_mapped with flips 1).
  void segment_once(std::span<const Point> points, uint8_t* labels, float* probabilities);
  // flips > 1: the passes over the mirrored copies, their probabilities mirrored back and summed
  // in the backend's memory (Backend::mirror_add), the labels the sum's arg-max and the
  // probabilities the sum over flips, computed there too: on a GPU only the result comes down.
  // Stage times are the passes' sums (the sum and its arg-max count as predict).
  void segment_flipped(std::span<const Point> points, uint8_t* labels, float* probabilities);
  // Loads the points and queues one pass (the recorded graph where the backend records), up to
  // the labels and, with_probabilities, the softmax; nothing comes down.
  void queue_pass(std::span<const Point> points, bool with_probabilities);
  // The labels (H x W bytes) and, where probabilities is not null, K x H x W floats down from the
  // backend's memory; times the download.
  void download(const uint8_t* device_labels, const float* device_probabilities, uint8_t* labels,
                float* probabilities);
  // Everything after the upload on the whole point buffer, shaped by the capacity: what a graph
  // records (and, once, runs uncaptured to grow every buffer first).
  void queue_recordable(bool probabilities);
  // The same on exactly the scan's points, with stage timing where it is on.
  void queue_direct(const Ref& points, bool probabilities);
  void queue_predictions(bool probabilities);
  // The network's evaluation forward on the filled inputs, its PFN stopping at the gather's P'.
  void run_network();

  ModelConfig model_;
  SegmenterOptions options_;
  std::unique_ptr<Backend> backend_;
  std::unique_ptr<PillarSegNet> net_;
  ScanPipeline pipeline_;
  InputMapping input_;
  std::vector<Point> mapped_;  // the mapped copy of the last scan's points (its capacity kept)
  // flips > 1: a mirrored copy's points; the running sum of probabilities (1, K, H, W) and its
  // arg-max (1, H, W) in the backend's memory (flip_arena_, made on the first flipped scan).
  std::vector<Point> mirrored_;
  std::unique_ptr<Arena> flip_arena_;
  Ref flip_sum_;
  LRef flip_labels_;
  bool time_stages_ = false;
  StageTimes times_;
  // The recorded pipelines, without and with the probabilities, and what they were recorded on.
  struct Recording {
    std::unique_ptr<CapturedGraph> graph;
    int64_t buffer_generation = -1, model_generation = -1;  // the pipeline's and the model's
  };
  std::array<Recording, 2> recordings_;
};

// A segmenter for a checkpoint: the run config of config_path when given (its grid, model and
// input mapping win), else the checkpoint's, else (a weights-only file) the architecture of its
// tensor shapes on the paper's grid; the weights loaded and checked. With options.precision int8
// (asked, not what runs) the weights must carry calibrated input scales: an uncalibrated checkpoint
// is refused on every CPU, also on one whose INT8 falls back to FP32, so that it fails where it is
// made and not first where it is deployed. Errors name the file and what is wrong.
std::unique_ptr<ScanSegmenter> open_segmenter(const std::filesystem::path& weights,
                                              const std::filesystem::path& config_path,
                                              const SegmenterOptions& options);
// The same for a checkpoint already read from `weights` and its run config (config_for).
std::unique_ptr<ScanSegmenter> open_segmenter(const Checkpoint& checkpoint, const RunConfig& config,
                                              const std::filesystem::path& weights,
                                              const SegmenterOptions& options);

}  // namespace pillarseg
