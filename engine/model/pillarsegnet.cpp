// PillarSegNet as two op graphs (engine/model/graph.hpp): the evaluation forward, and the
// training step (forward, loss, backward). build_model_graph() (engine/model/model_graph.hpp)
// emits every node in the order the backend runs it, the graph's lifetime planner places the
// activations of each in one block, and execute() runs a range of nodes on the backend through
// their op records (engine/model/op_record.hpp).
#include "engine/model/pillarsegnet.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <initializer_list>
#include <string>
#include <utility>
#include <vector>

#include "core/error.hpp"
#include "core/ops.hpp"
#include "engine/model/graph.hpp"
#include "engine/model/model_graph.hpp"
#include "engine/model/memory_estimate.hpp"

namespace pillarseg {

// One planned graph and its memory.
struct GraphPlan : ModelGraph {
  int batch = -1;
  int64_t pillar_capacity = -1;
  Precision precision = Precision::F32;  // of its 16-bit nodes
  std::unique_ptr<Arena> arena;
  uint8_t* base = nullptr;
  bool built() const { return batch > 0; }
};

// The modules, the two plans and the state between calls.
struct PillarSegNet::Impl : Modules {
  GraphPlan eval, train;
  GraphPlan* current = nullptr;
  LossSpec loss_spec;
  Precision precision = Precision::F32;        // of the evaluation convolutions
  std::map<std::string, Int8Input> int8_inputs;  // INT8: the U-Net's calibrated inputs
  PillarSegNet::ConvInputObserver observer;    // calibration
  Precision train_precision = Precision::F32;  // of the training step's convolutions
  // Pillar buffers are planned for a capacity that grows with headroom (a slowly rising pillar
  // count does not re-plan every batch); the nodes run on the current batch's rows.
  int64_t pillar_capacity = 0, pillar_rows = 0;
  bool loss_gradient_ready = false;
  ReplicaSum* replicas = nullptr;  // set_replicas
  IRef live_rows;                  // set_live_pillar_rows
  int64_t memory_generation = 0;
  // The resolved outputs of the current plan.
  Ref logits, d_logits, probs, coefficients;
  LRef labels, predicted;
  // The evaluation plan's prepared 16-bit weights (its persistent tensors) are those of the
  // parameters at generation prepared_parameters, in the plan of memory generation
  // prepared_memory (-1: none prepared).
  uint64_t prepared_parameters = 0;
  int64_t prepared_memory = -1;
  // The evaluation forward recorded as a graph (backends with supports_capture()), valid until
  // the next re-plan; cells (capacity, 3) of -1, the padding rows' cells (outside every canvas).
  std::unique_ptr<CapturedGraph> eval_graph;
  std::vector<int32_t> padding_cells;
};


PillarSegNet::PillarSegNet(const ModelConfig& config, Backend& backend, uint64_t seed)
    : config_(config), backend_(backend), params_(backend), impl_(std::make_unique<Impl>()) {
  config_.validate();
  // The least any use of the model needs (an evaluation forward of one sample), before the
  // parameters are allocated; each plan is checked again, exactly, before its block is.
  check_model_memory(config_, 1, /*training=*/false, backend_.memory_budget());
  static_cast<Modules&>(*impl_) = declare_modules(config_, params_);
  params_.finalize(seed);
}

PillarSegNet::~PillarSegNet() = default;

// The graph of the evaluation forward (training: the training step) for `batch` samples and the
// current pillar capacity.
void PillarSegNet::build_graph(GraphPlan& p, int batch, bool training) {
  Impl& m = *impl_;
  p.precision = training ? m.train_precision : m.precision;
  build_model_graph(p, config_, m, params_, &backend_, batch, training, p.precision, m.pillar_capacity,
                    &m.int8_inputs);
  p.batch = batch;
  p.pillar_capacity = m.pillar_capacity;
}

void PillarSegNet::set_batchnorm_momentum(float momentum) {
  PS_CHECK(momentum <= 1, "BatchNorm momentum must be at most 1, got {}", momentum);
  for (BnParams& bn : impl_->bns) bn.momentum = momentum > 0 ? momentum : bn.module_momentum;
}

void PillarSegNet::set_replicas(ReplicaSum* replicas) {
  std::string why;
  PS_CHECK(replicas == nullptr || backend_.supports_synchronized_batchnorm(&why), "data-parallel training: {}", why);
  impl_->replicas = replicas;
}

namespace {

template <class T>
RefT<T> typed(void* data, Shape shape) {
  return RefT<T>{static_cast<T*>(data), std::move(shape)};
}

}  // namespace

// The memory of tensor `id` of plan p, with the current pillar rows for dynamic tensors.
template <class T>
RefT<T> PillarSegNet::bind(const GraphPlan& p, int id) {
  if (id < 0) return RefT<T>{};
  const GraphTensor& t = p.graph.at(id);
  Shape shape = t.shape;
  if (t.dynamic_rows) shape[0] = impl_->pillar_rows;
  if (t.parameter >= 0) {
    const Ref r = t.gradient ? params_.grad(t.parameter) : params_.graph_value(t.parameter);
    return typed<T>(r.data, std::move(shape));
  }
  size_t offset = 0;
  int root = id;
  while (p.graph.at(root).view_of >= 0) {
    offset += p.graph.at(root).view_offset;
    root = p.graph.at(root).view_of;
  }
  return typed<T>(p.base + p.graph.at(root).offset + offset, std::move(shape));
}

BatchNormRefs PillarSegNet::batchnorm_refs(const GraphPlan& p, const GraphNode& n, int save_mean, int save_invstd) {
  const BnParams& b = impl_->bns[static_cast<size_t>(n.batchnorm)];
  BatchNormRefs r;
  r.gamma = params_.graph_value(b.gamma);
  r.beta = params_.graph_value(b.beta);
  r.running_mean = params_.graph_value(b.mean);
  r.running_var = params_.graph_value(b.var);
  r.save_mean = bind<float>(p, save_mean);
  r.save_invstd = bind<float>(p, save_invstd);
  r.eps = b.eps;
  r.momentum = b.momentum;
  r.replicas = &p == &impl_->train ? impl_->replicas : nullptr;  // the training step's BatchNorms
  return r;
}

namespace {

bool prepares_weights(OpKind op) {
  return op == OpKind::PrepareConvWeights || op == OpKind::PrepareConvTransposeWeights;
}

}  // namespace

// Runs nodes [begin, end) of plan p on the backend (the loss node returns its value). In the
// evaluation plan the weight preparations run only with prepared_weights_only, which runs nothing
// else (refresh_prepared_weights()).
double PillarSegNet::execute(const GraphPlan& p, size_t begin, size_t end, bool prepared_weights_only) {
  Impl& m = *impl_;
  Backend& be = backend_;
  const std::vector<GraphNode>& nodes = p.graph.nodes();
  double loss_value = 0;
  double last = time_stages_ ? be.clock_ms() : 0.0;
  const auto lap = [&](Stage stage) {
    const double now = be.clock_ms();
    const double elapsed = now - last;
    last = now;
    switch (stage) {
      case Stage::Pfn: stage_times_.pfn += elapsed; break;
      case Stage::Scatter: stage_times_.scatter += elapsed; break;
      case Stage::Occupancy: stage_times_.occupancy += elapsed; break;
      case Stage::UNet: stage_times_.unet += elapsed; break;
      case Stage::Head: stage_times_.head += elapsed; break;
      case Stage::Loss:
      case Stage::Backward: break;
    }
  };
  // The executor's view of this plan (engine/model/op_record.hpp).
  class Context final : public OpContext {
   public:
    Context(PillarSegNet& net, const GraphPlan& plan) : net_(net), plan_(plan) {}
    Backend& backend() override { return net_.backend_; }
    const Graph& graph() const override { return plan_.graph; }
    void* data(int id) override { return net_.bind<uint8_t>(plan_, id).data; }
    Shape shape(int id) const override { return net_.bind<uint8_t>(plan_, id).shape; }
    BatchNormRefs batchnorm(const GraphNode& n, int save_mean, int save_invstd) override {
      return net_.batchnorm_refs(plan_, n, save_mean, save_invstd);
    }
    void batchnorm_ran(const GraphNode& n) override {
      net_.params_.counters()[net_.impl_->bns[static_cast<size_t>(n.batchnorm)].counter] += 1;
    }
    int64_t pillar_rows() const override { return net_.impl_->pillar_rows; }
    IRef live_rows() const override { return net_.impl_->live_rows; }
    LossSpec loss_spec() const override { return net_.impl_->loss_spec; }

   private:
    PillarSegNet& net_;
    const GraphPlan& plan_;
  };
  Context context(*this, p);
  for (size_t i = begin; i < end; ++i) {
    const GraphNode& n = nodes[i];
    if (&p == &m.eval && prepares_weights(n.op) != prepared_weights_only) {
      if (time_stages_ && (i + 1 == end || nodes[i + 1].stage != n.stage)) lap(n.stage);
      continue;
    }
    if (m.observer && &p == &m.eval) observe_conv_input(p, n, context);
    const double op_start = time_ops_ ? be.clock_ms() : 0.0;
    const Backend::Counters counted_before = time_ops_ ? be.counters() : Backend::Counters{};
    const double value = op_record(n.op).run(context, n);
    if (n.op == OpKind::Loss) loss_value = value;
    if (time_ops_) {
      OpTime& t = op_times_[op_label(p.graph, n, be.device())];
      t.ms += be.clock_ms() - op_start;
      t.flops += n.flops;
      t.bytes += static_cast<double>(p.graph.node_bytes(i, m.pillar_rows));
      t.matrix_units = on_matrix_units(p.graph, n);
      t.int8_units = on_int8_units(p.graph, n);
      const Backend::Counters counted = be.counters();
      const auto add_counted = [](double& total, int64_t before, int64_t after) {
        if (before < 0 || after < 0) return;
        total = std::max(total, 0.0) + static_cast<double>(after - before);
      };
      add_counted(t.tensor_core_flops, counted_before.tensor_core_flops, counted.tensor_core_flops);
      add_counted(t.async_copy_bytes, counted_before.async_copy_bytes, counted.async_copy_bytes);
      ++t.calls;
    }
    if (time_stages_ && (i + 1 == end || nodes[i + 1].stage != n.stage)) lap(n.stage);
  }
  return loss_value;
}

void PillarSegNet::set_precision(Precision precision) {
  Impl& m = *impl_;
  if (precision == m.precision) return;
  std::string why;
  PS_CHECK(backend_.supports_precision(precision, &why), "--precision {}: {}", precision_name(precision), why);
  m.precision = precision;
  m.eval.batch = -1;  // planned again at the next evaluation forward
  m.eval_graph.reset();
}

Precision PillarSegNet::precision() const { return impl_->precision; }

void PillarSegNet::set_int8_inputs(std::map<std::string, Int8Input> inputs) {
  Impl& m = *impl_;
  for (const auto& [key, input] : inputs)
    PS_CHECK(std::isfinite(input.scale) && input.scale > 0, "INT8 input scale of {}: {} is not a positive number", key,
             input.scale);
  m.int8_inputs = std::move(inputs);
  m.eval.batch = -1;  // planned again at the next evaluation forward
  m.eval_graph.reset();
}

const std::map<std::string, Int8Input>& PillarSegNet::int8_inputs() const { return impl_->int8_inputs; }

void PillarSegNet::set_conv_input_observer(ConvInputObserver observer) {
  impl_->observer = std::move(observer);
  impl_->eval_graph.reset();
}

bool PillarSegNet::observing_conv_inputs() const { return static_cast<bool>(impl_->observer); }

// The U-Net's convolutions of an evaluation graph and their inputs, for the observer.
void PillarSegNet::observe_conv_input(const GraphPlan& p, const GraphNode& n, OpContext& context) {
  if (n.stage != Stage::UNet) return;
  int x = -1, w = -1;
  switch (n.op) {
    case OpKind::Conv2d:
    case OpKind::Conv2dBnReluEval:
    case OpKind::ConvTranspose2d: {
      const auto a = n.as<Conv2dArgs>();
      x = a.x, w = a.w;
      break;
    }
    default:
      return;
  }
  const GraphTensor& weight = p.graph.at(w);
  if (weight.parameter < 0) return;
  const bool winograd = n.op != OpKind::ConvTranspose2d && op::winograd_3x3(weight.shape, n.pad);
  impl_->observer(quantization_key(params_.entries().at(static_cast<size_t>(weight.parameter)).name),
                  context.tensor(x), winograd);
}

void PillarSegNet::set_training_precision(Precision precision) {
  Impl& m = *impl_;
  if (precision == m.train_precision) return;
  std::string why;
  PS_CHECK(backend_.supports_training_precision(precision, &why), "--precision {} for training: {}",
           precision_name(precision), why);
  m.train_precision = precision;
  m.train.batch = -1;  // planned again at the next training forward
}

Precision PillarSegNet::training_precision() const { return impl_->train_precision; }

void PillarSegNet::plan(int batch, bool training) {
  Impl& m = *impl_;
  GraphPlan& p = training ? m.train : m.eval;
  if (!p.built() || p.batch != batch || p.pillar_capacity != m.pillar_capacity) {
    const bool batch_changed = p.batch != batch;
    check_index_limits(config_, batch);
    build_graph(p, batch, training);
    const size_t bytes = p.graph.plan();
    p.batch = -1;  // planned again at the next call unless this one places the graph
    // The block is allocated after the one held is released.
    const size_t held = p.arena ? p.arena->capacity() : 0;
    if (bytes > held) {
      MemoryBudget budget = backend_.memory_budget();
      if (held > 0) {
        budget.bytes = budget.bytes > ~uint64_t{0} - held ? ~uint64_t{0} : budget.bytes + held;
        budget.description += fmt::format(", and the {} of the model's previous plan", format_bytes(held));
      }
      require_memory(bytes,
                     fmt::format("the {} of PillarSegNet on a {} x {} grid (batch {}, {} pillar rows)",
                                 training ? "training step" : "evaluation forward", config_.grid.width(),
                                 config_.grid.height(), batch, m.pillar_capacity),
                     budget);
    }
    // Kept while the batch size stays, so that switching between training and eval does not
    // allocate; another batch size (or a new pillar capacity) plans again.
    if (!p.arena) p.arena = std::make_unique<Arena>(backend_);
    if (batch_changed) p.arena->release();
    p.arena->reserve(bytes);
    p.arena->reset();
    p.base = p.arena->take<uint8_t>({static_cast<int64_t>(bytes)}).data;
    p.batch = batch;
    ++m.memory_generation;  // every Ref of the plan may have moved
    if (!training) m.eval_graph.reset();
  }
  m.current = &p;
  m.logits = bind<float>(p, p.logits);
  m.d_logits = bind<float>(p, p.d_logits);
  m.probs = bind<float>(p, p.probs);
  m.coefficients = bind<float>(p, p.coefficients);
  m.labels = bind<uint8_t>(p, p.labels);
  m.predicted = bind<uint8_t>(p, p.predicted);
  logits_ = m.logits;
}

void PillarSegNet::plan_pillars(int64_t pillars) {
  Impl& m = *impl_;
  if (!config_.pillar_input) return;
  if (pillars > m.pillar_capacity) {
    // The PFN's point rows (pillars x N) are int32 (kernels/pfn.cu), and so are pillar ids.
    const int64_t N = config_.max_points_per_pillar;
    require_int32_count({pillars, N}, fmt::format("{} pillars x {} points a pillar", pillars, N),
                        "point rows of the PFN");
    m.eval_graph.reset();  // it names the old buffers
    // Grow with headroom so that a slowly rising pillar count does not re-plan every batch.
    m.pillar_capacity = pillar_capacity_for(pillars, N);
    m.padding_cells.assign(static_cast<size_t>(m.pillar_capacity) * 3, -1);
  }
}

size_t PillarSegNet::activation_bytes() const {
  const Impl& m = *impl_;
  return m.current ? m.current->graph.planned_bytes() : 0;
}

const Graph& PillarSegNet::graph(bool training) const { return training ? impl_->train.graph : impl_->eval.graph; }

std::string PillarSegNet::memory_report(bool training) const { return graph(training).memory_report(); }

void PillarSegNet::set_live_pillar_rows(const IRef& live_rows) {
  impl_->live_rows = live_rows;
  live_rows_data("set_live_pillar_rows", live_rows);  // empty or one int32
}

PillarSegNet::Inputs PillarSegNet::prepare(int batch, int64_t pillar_rows, bool training) {
  Impl& m = *impl_;
  PS_CHECK(batch >= 1, "prepare: batch size must be >= 1, got {}", batch);
  PS_CHECK(pillar_rows >= 0, "prepare: pillar rows must be >= 0, got {}", pillar_rows);
  plan_pillars(pillar_rows);
  m.pillar_rows = config_.pillar_input ? pillar_rows : 0;
  plan(batch, training);
  const GraphPlan& p = *m.current;
  Inputs in;
  in.pillar_points = bind<float>(p, p.pillar_points);
  in.pillar_cells = bind<int32_t>(p, p.pillar_cells);
  in.occupancy = bind<float>(p, p.occupancy_input);
  in.grid_map = bind<float>(p, p.grid_map_input);
  return in;
}

int64_t PillarSegNet::memory_generation() const { return impl_->memory_generation; }

void PillarSegNet::forward(const ModelBatch& batch, bool training) {
  Impl& m = *impl_;
  Backend& be = backend_;
  const int H = config_.grid.height(), W = config_.grid.width();
  PS_CHECK(batch.batch >= 1, "forward: batch size must be >= 1, got {}", batch.batch);
  stage_times_ = StageTimes{};
  m.loss_gradient_ready = false;
  // Stage clock: the upload's time; run() times the stages after it.
  const double start = time_stages_ ? be.clock_ms() : 0.0;
  // The evaluation forward replays a recorded graph where the backend records them (and stage
  // and op timing, which wait between stages and ops, are off). The graph runs the pillar stream at the pillar
  // capacity: rows past this batch's P hold zero points and cells (-1, -1, -1), which the scatter
  // skips, so one recording serves every pillar count up to the capacity, the count itself never
  // reaching the device work; a re-plan (another batch size, more pillars than the capacity)
  // records again.
  const bool replay = !training && !time_stages_ && !time_ops_ && !m.observer && be.supports_capture();

  int64_t P = 0;
  if (config_.pillar_input) {
    P = batch.pillar_points.rank() == 3 ? batch.pillar_points.dim(0) : 0;
    PS_CHECK(batch.pillar_points.rank() == 3 || batch.pillar_points.numel() == 0,
             "forward: pillar_points must be (P, N, 10), got {}", shape_str(batch.pillar_points.shape()));
    if (P > 0) {
      PS_CHECK(batch.pillar_points.dim(1) == config_.max_points_per_pillar && batch.pillar_points.dim(2) == 10,
               "forward: pillar_points must be (P, {}, 10), got {}", config_.max_points_per_pillar,
               shape_str(batch.pillar_points.shape()));
      PS_CHECK(batch.pillar_cells.shape() == (Shape{P, 3}), "forward: pillar_cells must be ({}, 3), got {}", P,
               shape_str(batch.pillar_cells.shape()));
    }
  }
  plan_pillars(P);
  m.pillar_rows = config_.pillar_input ? (replay ? m.pillar_capacity : P) : 0;
  plan(batch.batch, training);
  const GraphPlan& p = *m.current;
  if (config_.pillar_input) {
    const Ref points = bind<float>(p, p.pillar_points);
    const IRef cells = bind<int32_t>(p, p.pillar_cells);
    const size_t point_bytes = static_cast<size_t>(P) * static_cast<size_t>(config_.max_points_per_pillar) * 10 *
                               sizeof(float);
    const size_t cell_bytes = static_cast<size_t>(P) * 3 * sizeof(int32_t);
    if (P > 0) {
      be.upload(points.data, batch.pillar_points.data(), point_bytes);
      be.upload(cells.data, batch.pillar_cells.data(), cell_bytes);
    }
    if (replay) {
      be.fill_zero(reinterpret_cast<char*>(points.data) + point_bytes, points.bytes() - point_bytes);
      be.upload(reinterpret_cast<char*>(cells.data) + cell_bytes, m.padding_cells.data(), cells.bytes() - cell_bytes);
    }
  }
  if (config_.occupancy != OccupancyInput::None) {
    const Ref occupancy = bind<float>(p, p.occupancy_input);
    const Shape expected{batch.batch, config_.occupancy_input_channels(), H, W};
    PS_CHECK(batch.occupancy.shape() == expected, "forward: occupancy input must be {}, got {}", shape_str(expected),
             shape_str(batch.occupancy.shape()));
    be.upload(occupancy.data, batch.occupancy.data(), occupancy.bytes());
  }
  if (config_.grid_map_input) {
    const Ref grid_map = bind<float>(p, p.grid_map_input);
    const Shape expected{batch.batch, 6, H, W};
    PS_CHECK(batch.grid_map.shape() == expected, "forward: grid_map input must be {}, got {}", shape_str(expected),
             shape_str(batch.grid_map.shape()));
    be.upload(grid_map.data, batch.grid_map.data(), grid_map.bytes());
  }
  if (time_stages_) {
    run(training);
    stage_times_.upload = run_started_ms_ - start;
    return;
  }
  if (!replay) {
    run(training);
    return;
  }
  // The weights are prepared outside the recording, which so holds none, and only when they
  // changed.
  refresh_prepared_weights();
  if (!m.eval_graph || !m.eval_graph->valid()) m.eval_graph = be.capture([&] { run(false); });
  m.eval_graph->replay();
}

// The device work of a forward: the plan's forward nodes.
void PillarSegNet::run(bool training) {
  Impl& m = *impl_;
  PS_CHECK(m.current != nullptr && m.current == (training ? &m.train : &m.eval),
           "PillarSegNet::run({}): plan the inputs first (prepare() or forward())", training ? "training" : "eval");
  stage_times_ = StageTimes{};
  m.loss_gradient_ready = false;
  run_started_ms_ = time_stages_ ? backend_.clock_ms() : 0.0;
  if (training) {
    params_.mark_changed();  // the BatchNorms' running statistics
  } else {
    refresh_prepared_weights();
  }
  execute(*m.current, 0, m.current->forward_end);
}

void PillarSegNet::refresh_prepared_weights() {
  Impl& m = *impl_;
  if (!m.eval.built()) return;
  if (m.prepared_memory == m.memory_generation && m.prepared_parameters == params_.generation()) return;
  execute(m.eval, 0, m.eval.forward_end, /*prepared_weights_only=*/true);
  m.prepared_memory = m.memory_generation;
  m.prepared_parameters = params_.generation();
}

void PillarSegNet::queue_predictions(bool probabilities) {
  Impl& m = *impl_;
  PS_CHECK(m.current != nullptr, "queue_predictions() before a forward");
  backend_.argmax(m.logits, m.predicted);
  if (probabilities) backend_.softmax(m.logits, m.probs);
}

const LRef& PillarSegNet::predicted() const { return impl_->predicted; }
const Ref& PillarSegNet::probs() const { return impl_->probs; }

double PillarSegNet::loss(const Tensor<uint8_t>& labels, const LossSpec& spec,
                          const std::array<float, 13>& coefficients) {
  Impl& m = *impl_;
  PS_CHECK(m.current != nullptr, "loss() before forward()");
  PS_CHECK(labels.shape() == m.labels.shape, "loss: labels must be {}, got {}", shape_str(m.labels.shape),
           shape_str(labels.shape()));
  backend_.upload(m.labels.data, labels.data(), m.labels.bytes());
  backend_.upload(m.coefficients.data, coefficients.data(), m.coefficients.bytes());
  m.loss_spec = spec;
  const double value = execute(*m.current, m.current->loss_node, m.current->loss_node + 1);
  m.loss_gradient_ready = true;
  return value;
}

void PillarSegNet::backward(GradientListener* listener, int64_t bucket_elements) {
  Impl& m = *impl_;
  PS_CHECK(m.current == &m.train, "backward() needs a training-mode forward first (the eval forward keeps no "
                                  "activations for it)");
  PS_CHECK(m.loss_gradient_ready, "backward() needs loss() after the training forward (each backward consumes "
                                  "the logits' gradient that loss() writes)");
  m.loss_gradient_ready = false;
  const size_t first = m.train.loss_node + 1, end = m.train.graph.size();
  if (listener == nullptr) {
    execute(m.train, first, end);
    return;
  }
  const std::vector<GradientBucket> buckets = gradient_buckets(bucket_elements);
  size_t next = 0;
  for (size_t i = first; i < end; ++i) {
    execute(m.train, i, i + 1);
    for (; next < buckets.size() && buckets[next].after <= i; ++next)
      listener->bucket_ready(buckets[next].offset, buckets[next].count);
    listener->between_nodes();
  }
  PS_CHECK(next == buckets.size(), "backward: {} of {} gradient buckets were never ready", buckets.size() - next,
           buckets.size());
}

std::vector<GradientBucket> PillarSegNet::gradient_buckets(int64_t bucket_elements) const {
  const Impl& m = *impl_;
  PS_CHECK(m.train.built(), "gradient_buckets() needs a training plan (a training-mode forward first)");
  std::vector<int64_t> offsets;
  for (const ParamEntry& e : params_.entries()) offsets.push_back(e.trainable ? e.offset : -1);
  return m.train.graph.gradient_buckets(offsets, params_.num_trainable(), bucket_elements);
}

Tensor<float> PillarSegNet::download_logits() const {
  Tensor<float> out(logits_.shape);
  backend_.download(out.data(), logits_.data, logits_.bytes());
  return out;
}

Tensor<float> PillarSegNet::probabilities() {
  Impl& m = *impl_;
  backend_.softmax(m.logits, m.probs);
  Tensor<float> out(m.probs.shape);
  backend_.download(out.data(), m.probs.data, m.probs.bytes());
  return out;
}

Tensor<uint8_t> PillarSegNet::predict_labels() {
  Impl& m = *impl_;
  backend_.argmax(m.logits, m.predicted);
  Tensor<uint8_t> out(m.predicted.shape);
  backend_.download(out.data(), m.predicted.data, m.predicted.bytes());
  return out;
}

}  // namespace pillarseg
