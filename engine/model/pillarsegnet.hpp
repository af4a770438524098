// PillarSegNet (DESIGN.md section 2) on any Backend: pillar feature net + scatter, optional
// occupancy stream (Conv3x3 -> BN -> ReLU to Q channels) and grid-map layers, concatenated
// into the input canvas (B, I, H, W); the authors' U-Net without its input block (bilinear or
// transposed-convolution upsampling); a 1x1 head to 12 classes. Forward keeps what backward
// needs; backward writes every parameter gradient (overwriting).
//
// The model is two explicit op graphs (engine/model/graph.hpp), built per batch size, pillar
// capacity and mode: the evaluation forward, and the training step (forward, loss, backward).
// One lifetime planner places each graph's tensors in one block, overlaying those whose
// lifetimes do not meet: eval's activation dies after its last reader (a skip tensor after its
// decoder's concat); training keeps what the backward reads until it reads it, and each
// gradient lives from the op that writes it to the one that consumes it. The pillar buffers are
// planned for a capacity that grows only when a batch has more pillars than any before, so the
// steady-state loop allocates nothing, and a recorded evaluation graph stays valid until then.
// FLOP counts, the per-stage timing and the memory report read the same graphs.
#pragma once

#include <array>
#include <functional>
#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "core/tensor.hpp"
#include "engine/backend/backend.hpp"
#include "engine/model/config.hpp"
#include "engine/model/graph.hpp"
#include "engine/model/parameters.hpp"

namespace pillarseg {

class Graph;
class OpContext;
struct GraphNode;
struct GraphPlan;

// One batch of network inputs, on the host.
struct ModelBatch {
  int batch = 1;
  Tensor<float> pillar_points;   // (P, N, 10) decorated points of all samples
  Tensor<int32_t> pillar_cells;  // (P, 3): sample index, iy, ix
  Tensor<float> occupancy;       // (B, 1 or Z, H, W) when the config has an occupancy stream
  Tensor<float> grid_map;        // (B, 6, H, W) when the config has the grid-map input
};

class PillarSegNet {
 public:
  PillarSegNet(const ModelConfig& config, Backend& backend, uint64_t seed = 0);
  ~PillarSegNet();
  PillarSegNet(const PillarSegNet&) = delete;
  PillarSegNet& operator=(const PillarSegNet&) = delete;

  const ModelConfig& config() const { return config_; }
  Backend& backend() { return backend_; }
  ParameterSet& parameters() { return params_; }
  const ParameterSet& parameters() const { return params_; }

  // Time of each stage of the last forward, in ms (upload, pfn, scatter, occupancy, unet, head),
  // when timing is on: read from Backend::clock_ms() at every stage boundary (it waits for the
  // device; CUDA events on the CUDA backend).
  struct StageTimes {
    double upload = 0, pfn = 0, scatter = 0, occupancy = 0, unet = 0, head = 0;
  };
  void set_stage_timing(bool on) { time_stages_ = on; }
  const StageTimes& stage_times() const { return stage_times_; }
  // Per-op timing (where a benchmark's time goes): while on, every node of the op graph that a
  // forward, loss or backward runs is timed by Backend::clock_ms() and added, with the node's
  // FLOPs and bytes, to the total of its op and dtype (op_label(), engine/model/op_record.hpp),
  // until cleared.
  // It waits for the device after every node, and the evaluation forward is not replayed from a
  // recorded graph meanwhile. bytes: what the node must move at the least, every tensor it reads
  // or writes once (Graph::node_bytes, with the pillar rows of the run); tensor_core_flops and
  // async_copy_bytes: what the backend counted the node's kernels issue (Backend::Counters; -1
  // where it does not count).
  struct OpTime {
    double ms = 0, flops = 0, bytes = 0;
    bool matrix_units = false;  // on_matrix_units(): the roofline's 16-bit peak
    bool int8_units = false;    // on_int8_units(): its INT8 peak
    double tensor_core_flops = -1, async_copy_bytes = -1;
    int64_t calls = 0;
  };
  void set_op_timing(bool on) { time_ops_ = on; }
  const std::map<std::string, OpTime>& op_times() const { return op_times_; }
  void clear_op_times() { op_times_.clear(); }

  // The arithmetic of the evaluation forward's U-Net: BF16 or FP16 convolutions and activations
  // on a backend that supports_precision() it (the CUDA backend on compute capability 8.0 or
  // later, the emulation, the CPU with AVX512_BF16), else throws pillarseg::Error with the
  // reason. The evaluation graph is planned again at the next forward.
  // INT8 (DESIGN.md section 10) on a backend that supports it, with the U-Net's input scales
  // set first (set_int8_inputs, or a calibrated checkpoint's through load_weights).
  void set_precision(Precision precision);
  Precision precision() const;
  // The calibrated quantization of the U-Net's convolution inputs for INT8 (per-tensor scales,
  // signed or non-negative), by quantization_key (engine/model/model_graph.hpp); the evaluation
  // graph is planned again.
  void set_int8_inputs(std::map<std::string, Int8Input> inputs);
  const std::map<std::string, Int8Input>& int8_inputs() const;
  // Calibration: while set, every U-Net convolution of an evaluation forward hands its input (the
  // backend's memory, with its dtype) and its key to `observer` before it runs; the forward then
  // runs node by node (no recorded graph); `winograd`: the convolution is 3x3 with padding 1
  // (Winograd F(2x2, 3x3) applies to it).
  using ConvInputObserver = std::function<void(const std::string& key, const TensorRef& input, bool winograd)>;
  void set_conv_input_observer(ConvInputObserver observer);
  bool observing_conv_inputs() const;  // an observer is set: no recorded graph may hold the forward
  // The training step's convolutions (forward, input and weight gradients) in BF16 or FP16 on
  // the tensor cores, with activations, BatchNorm, the loss, gradients, the FP32 master weights
  // and the optimiser state in FP32, on a backend that supports_training_precision() it (the
  // CUDA backend), else throws with the reason. The training graph is planned again.
  void set_training_precision(Precision precision);
  Precision training_precision() const;

  // Runs the network on host inputs (uploaded first); training: batch statistics (and
  // running-statistic updates). Evaluation on a backend that captures graphs (and with stage
  // timing off) records its device work once per planned shape and replays it (see forward() in
  // the .cpp).
  void forward(const ModelBatch& batch, bool training);

  // The network's inputs in the backend's memory, for an input pipeline that prepares them there
  // (engine/pipeline/): pillar_points (rows, N, 10), pillar_cells (rows, 3) (sample, iy, ix; rows
  // of -1 are skipped), occupancy (B, 1 or Z, H, W), grid_map (B, 6, H, W); the streams the
  // config lacks are empty. prepare() plans memory for `batch` samples, `pillar_rows` rows and
  // the mode (allocating only when they need more than before); run() then runs the network on
  // whatever the inputs hold, queueing device work only (no upload, download or wait), so that a
  // graph capture may record it. The Refs stay valid while memory_generation() is unchanged.
  struct Inputs {
    Ref pillar_points;
    IRef pillar_cells;
    Ref occupancy;
    Ref grid_map;
  };
  Inputs prepare(int batch, int64_t pillar_rows, bool training);
  // The evaluation PFN's live pillar rows: empty (the default), every row; else one int32 in the
  // backend's memory (a device pipeline's P', ScanPipeline::live_pillar_rows()), read when the
  // work runs: rows at or past it are inert (their cells are (-1, -1, -1)) and not computed. The
  // memory must stay valid while set; set it empty before the inputs are filled otherwise.
  void set_live_pillar_rows(const IRef& live_rows);
  void run(bool training);
  // Queues the evaluation plan's weight preparation (the 16-bit weights, BatchNorm folded in, of
  // a mixed-precision plan, kept in the plan from run to run) when the parameters
  // (ParameterSet::generation()) or the plan changed since it last ran; run(false) calls it
  // first. A caller that replays a recorded evaluation forward calls it before each replay: a
  // recording made while the weights were current holds no preparation.
  void refresh_prepared_weights();
  // Changes whenever the model moves memory that its Refs (inputs, activations, outputs) name.
  int64_t memory_generation() const;

  // After a forward: queues the arg-max class ids (B, H, W) into predicted() and, with
  // `probabilities`, the softmax into probs(), without waiting (device work only).
  void queue_predictions(bool probabilities);
  const LRef& predicted() const;
  const Ref& probs() const;
  // After forward: the mean loss over labelled cells of labels (B, H, W), and the gradient
  // of the logits, ready for backward(). coefficients: per class id 0..12.
  double loss(const Tensor<uint8_t>& labels, const LossSpec& spec, const std::array<float, 13>& coefficients);
  // After loss(): every parameter gradient. Once per loss() (it consumes the logits' gradient).
  // With a listener (data-parallel training): the gradient array in buckets of at least
  // bucket_elements floats (Graph::gradient_buckets; <= 0: one, after the last node), each
  // handed to listener->bucket_ready() as soon as the backward has queued its last write, and
  // listener->between_nodes() after every node.
  class GradientListener {
   public:
    virtual ~GradientListener() = default;
    virtual void bucket_ready(int64_t offset, int64_t count) = 0;
    virtual void between_nodes() = 0;
  };
  void backward(GradientListener* listener = nullptr, int64_t bucket_elements = 0);
  // The buckets backward() hands out, for the current training plan (after a training forward).
  std::vector<GradientBucket> gradient_buckets(int64_t bucket_elements) const;

  // The momentum of every BatchNorm's running statistics in training-mode forwards; 0 (or
  // less) restores each module's own (0.1 in the U-Net, 0.01 in the PFN and occupancy stream).
  // Recalibration sets 1/k before the k-th of K forwards: the running statistics become the
  // plain average of the K batches' statistics under the current weights.
  void set_batchnorm_momentum(float momentum);
  // Data-parallel training (DESIGN.md section 8): every training-mode BatchNorm normalises with
  // the statistics of the global batch, summed over the replicas (synchronised BatchNorm), on a
  // backend that supports_synchronized_batchnorm(); nullptr (the default): this process's batch.
  // The replicas must outlive the model or be reset first.
  void set_replicas(ReplicaSum* replicas);

  Ref logits() const { return logits_; }
  Tensor<float> download_logits() const;           // (B, 12, H, W)
  Tensor<float> probabilities();                   // softmax, (B, 12, H, W)
  Tensor<uint8_t> predict_labels();                // argmax class ids 1..12, (B, H, W)
  // Bytes of activation memory planned for the current batch shape and mode (the pillar
  // buffers included).
  size_t activation_bytes() const;
  // The op graph of the evaluation forward or of the training step as last planned (empty
  // before the first forward or prepare() of that mode), and its memory report.
  const Graph& graph(bool training) const;
  std::string memory_report(bool training) const;

  struct Impl;

 private:
  void plan(int batch, bool training);
  void plan_pillars(int64_t pillars);
  void build_graph(GraphPlan& p, int batch, bool training);
  template <class T>
  RefT<T> bind(const GraphPlan& p, int id);
  BatchNormRefs batchnorm_refs(const GraphPlan& p, const GraphNode& n, int save_mean, int save_invstd);
  double execute(const GraphPlan& p, size_t begin, size_t end, bool prepared_weights_only = false);
  void observe_conv_input(const GraphPlan& p, const GraphNode& n, OpContext& context);

  ModelConfig config_;
  Backend& backend_;
  ParameterSet params_;
  std::unique_ptr<Impl> impl_;
  Ref logits_;
  bool time_stages_ = false;
  StageTimes stage_times_;
  bool time_ops_ = false;
  std::map<std::string, OpTime> op_times_;
  double run_started_ms_ = 0;  // the backend clock when run() started (stage timing)
};

}  // namespace pillarseg
