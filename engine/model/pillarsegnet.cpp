#include "engine/model/pillarsegnet.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <functional>
#include <map>
#include <tuple>
#include <utility>
#include <vector>

#include "core/error.hpp"

namespace pillarseg {

namespace {

// Places tensors with known lifetimes (first and last step of the forward that uses them) in
// one block so that two tensors share bytes only when their lifetimes are disjoint. Greedy by
// size: each tensor, largest first, goes to the lowest 64-byte aligned offset that overlaps no
// placed tensor alive at the same time (the usual heuristic for static memory planning).
class LifetimePlanner {
 public:
  int add(size_t bytes, int first, int last) {
    items_.push_back({(bytes + 63) / 64 * 64, first, last, 0});
    return static_cast<int>(items_.size()) - 1;
  }
  void use_until(int id, int step) {
    Item& it = items_[static_cast<size_t>(id)];
    it.last = std::max(it.last, step);
  }
  // Assigns the offsets; returns the bytes of the block.
  size_t plan() {
    std::vector<size_t> order(items_.size());
    for (size_t i = 0; i < order.size(); ++i) order[i] = i;
    std::stable_sort(order.begin(), order.end(),
                     [&](size_t a, size_t b) { return items_[a].bytes > items_[b].bytes; });
    std::vector<size_t> placed;
    size_t total = 0;
    for (size_t i : order) {
      Item& it = items_[i];
      // Candidate offsets: 0 and the end of every placed tensor alive at the same time.
      std::vector<std::pair<size_t, size_t>> busy;  // [begin, end) of those tensors
      for (size_t j : placed) {
        const Item& other = items_[j];
        const bool meet = other.first <= it.last && it.first <= other.last;
        if (meet) busy.push_back({other.offset, other.offset + other.bytes});
      }
      std::sort(busy.begin(), busy.end());
      size_t offset = 0;
      for (const auto& [begin, end] : busy) {
        if (offset + it.bytes <= begin) break;
        offset = std::max(offset, end);
      }
      it.offset = offset;
      total = std::max(total, offset + it.bytes);
      placed.push_back(i);
    }
    return total;
  }
  size_t offset(int id) const { return items_[static_cast<size_t>(id)].offset; }

 private:
  struct Item {
    size_t bytes;
    int first, last;
    size_t offset;
  };
  std::vector<Item> items_;
};

// The training step's tensors in one block: each op of the forward, the loss and the backward
// is a step, a tensor lives from the step that first writes it to the last that reads it
// (keep(): until the next forward), and the LifetimePlanner overlays tensors whose lifetimes do
// not meet. The modules trace their ops in the order they run them (trace_forward and
// trace_backward beside forward and backward); bind() then points every traced Ref into the
// block.
class TensorPlan {
 public:
  static constexpr int kEnd = 1 << 30;

  // A tensor first written by the current step.
  template <class T>
  void add(RefT<T>& r, Shape shape) {
    r = RefT<T>{nullptr, std::move(shape)};
    const int id = planner_.add(r.bytes(), step_, step_);
    PS_CHECK(ids_.emplace(&r, id).second, "TensorPlan: a tensor was added twice");
    binders_.push_back([&r, id](uint8_t* base, const LifetimePlanner& planner) {
      r.data = reinterpret_cast<T*>(base + planner.offset(id));
    });
  }
  // r is the leading part of `whole` (an earlier add()), of its own shape: the two share one
  // lifetime, and a step that uses r uses `whole`.
  template <class T>
  void view(RefT<T>& r, const RefT<T>& whole, Shape shape) {
    r = RefT<T>{nullptr, std::move(shape)};
    PS_CHECK(r.bytes() <= whole.bytes(), "TensorPlan: a view is larger than its tensor");
    PS_CHECK(ids_.emplace(&r, id(&whole)).second, "TensorPlan: a tensor was added twice");
    binders_.push_back([&r, &whole](uint8_t*, const LifetimePlanner&) { r.data = whole.data; });
  }
  // The current step reads (or adds to) r.
  template <class T>
  void use(const RefT<T>& r) {
    planner_.use_until(id(&r), step_);
  }
  template <class T>
  void keep(const RefT<T>& r) {
    planner_.use_until(id(&r), kEnd);
  }
  void next() { ++step_; }

  // Places the tensors; returns the bytes of the block that bind() needs.
  size_t plan() { return planner_.plan(); }
  void bind(uint8_t* base) const {
    for (const auto& b : binders_) b(base, planner_);
  }

 private:
  int id(const void* ref) const {
    const auto it = ids_.find(ref);
    PS_CHECK(it != ids_.end(), "TensorPlan: a tensor is used before any step writes it");
    return it->second;
  }
  LifetimePlanner planner_;
  std::map<const void*, int> ids_;
  std::vector<std::function<void(uint8_t*, const LifetimePlanner&)>> binders_;
  int step_ = 0;
};

// Conv2d parameters: weight (O, I, k, k), optional bias (O).
struct ConvParams {
  int weight = -1, bias = -1;
  int in = 0, out = 0, k = 3, pad = 1;
};

ConvParams declare_conv(ParameterSet& ps, const std::string& prefix, int in, int out, int k, bool bias) {
  ConvParams c;
  c.in = in, c.out = out, c.k = k, c.pad = k / 2;
  const int64_t fan_in = int64_t{in} * k * k;
  c.weight = ps.add_trainable(prefix + ".weight", {out, in, k, k}, fan_in);
  if (bias) c.bias = ps.add_trainable(prefix + ".bias", {out}, fan_in);
  return c;
}

struct BnParams {
  int gamma = -1, beta = -1, mean = -1, var = -1;
  std::string counter;
  float eps = 1e-5f, momentum = 0.1f;
  float module_momentum = 0.1f;  // the PyTorch module's; `momentum` differs while recalibrating
  Ref save_mean, save_invstd;  // activations arena
};

BnParams declare_bn(ParameterSet& ps, const std::string& prefix, int channels, float eps, float momentum) {
  BnParams b;
  b.gamma = ps.add_trainable(prefix + ".weight", {channels}, 0, 1.0f);
  b.beta = ps.add_trainable(prefix + ".bias", {channels}, 0, 0.0f);
  b.mean = ps.add_buffer(prefix + ".running_mean", {channels}, 0.0f);
  b.var = ps.add_buffer(prefix + ".running_var", {channels}, 1.0f);
  b.counter = prefix + ".num_batches_tracked";
  ps.add_counter(b.counter);
  b.eps = eps, b.momentum = momentum, b.module_momentum = momentum;
  return b;
}

BatchNormRefs bn_refs(ParameterSet& ps, const BnParams& b) {
  BatchNormRefs r;
  r.gamma = ps.value(b.gamma);
  r.beta = ps.value(b.beta);
  r.running_mean = ps.value(b.mean);
  r.running_var = ps.value(b.var);
  r.save_mean = b.save_mean;
  r.save_invstd = b.save_invstd;
  r.eps = b.eps;
  r.momentum = b.momentum;
  return r;
}

// Conv -> BatchNorm -> ReLU with its activations.
struct ConvBnRelu {
  ConvParams conv;
  BnParams bn;
  Ref conv_out, out, d_conv_out, d_out;

  // The training forward's steps: conv, then BN + ReLU (saving the batch statistics). With
  // `container`, out is its leading channels: the container (of container_shape) is added with
  // it, so that a consumer that would copy out to the front of a larger tensor finds it there.
  void trace_forward(TensorPlan& p, const Ref& x, int batch, int h, int w, Ref* container = nullptr,
                     Shape container_shape = {}) {
    p.use(x);
    p.add(conv_out, {batch, conv.out, h, w});
    p.next();
    p.use(conv_out);
    if (container) {
      p.add(*container, std::move(container_shape));
      p.view(out, *container, {batch, conv.out, h, w});
    } else {
      p.add(out, {batch, conv.out, h, w});
    }
    p.add(bn.save_mean, {conv.out});
    p.add(bn.save_invstd, {conv.out});
    p.next();
  }
  // The backward's steps, d_out written by an earlier step: BN + ReLU backward, in place over
  // d_out (dead once read), then conv backward, which writes dx (a new tensor of dx_shape) when
  // given.
  void trace_backward(TensorPlan& p, const Ref& x, Ref* dx, Shape dx_shape) {
    p.use(conv_out), p.use(out), p.use(d_out), p.use(bn.save_mean), p.use(bn.save_invstd);
    p.view(d_conv_out, d_out, conv_out.shape);
    p.next();
    p.use(x), p.use(d_conv_out);
    if (dx) p.add(*dx, std::move(dx_shape));
    p.next();
  }
  void forward(Backend& be, ParameterSet& ps, const Ref& x, bool training) {
    Ref bias;
    if (conv.bias >= 0) bias = ps.value(conv.bias);
    BatchNormRefs r = bn_refs(ps, bn);
    if (!training) {  // running statistics: one fused pass, no conv_out kept
      be.conv2d_bn_relu_eval(x, ps.value(conv.weight), conv.bias >= 0 ? &bias : nullptr, r, conv.pad, out);
      return;
    }
    be.conv2d_forward(x, ps.value(conv.weight), conv.bias >= 0 ? &bias : nullptr, conv.pad, conv_out);
    be.batchnorm_relu_forward(conv_out, r, training, out);
    ps.counters()[bn.counter] += 1;
  }
  // Uses d_out (filled by the consumer); writes dx when given.
  void backward(Backend& be, ParameterSet& ps, const Ref& x, Ref* dx) {
    const BatchNormRefs r = bn_refs(ps, bn);
    Ref dgamma = ps.grad(bn.gamma), dbeta = ps.grad(bn.beta);
    be.batchnorm_relu_backward(conv_out, out, d_out, r, d_conv_out, dgamma, dbeta);
    Ref dw = ps.grad(conv.weight);
    Ref db;
    if (conv.bias >= 0) db = ps.grad(conv.bias);
    be.conv2d_backward(x, ps.value(conv.weight), d_conv_out, conv.pad, dx, dw, conv.bias >= 0 ? &db : nullptr);
  }
};

// [Conv3x3 (bias) -> BN -> ReLU] x 2, PyTorch module `double_conv` (indices 0,1 and 3,4).
struct DoubleConv {
  ConvBnRelu first, second;

  static DoubleConv declare(ParameterSet& ps, const std::string& prefix, int in, int out, int mid) {
    DoubleConv d;
    d.first.conv = declare_conv(ps, prefix + ".double_conv.0", in, mid, 3, true);
    d.first.bn = declare_bn(ps, prefix + ".double_conv.1", mid, 1e-5f, 0.1f);
    d.second.conv = declare_conv(ps, prefix + ".double_conv.3", mid, out, 3, true);
    d.second.bn = declare_bn(ps, prefix + ".double_conv.4", out, 1e-5f, 0.1f);
    return d;
  }
  // container: see ConvBnRelu::trace_forward (for the block's output).
  void trace_forward(TensorPlan& p, const Ref& x, int batch, int h, int w, Ref* container = nullptr,
                     Shape container_shape = {}) {
    first.trace_forward(p, x, batch, h, w);
    second.trace_forward(p, first.out, batch, h, w, container, std::move(container_shape));
  }
  void trace_backward(TensorPlan& p, const Ref& x, Ref* dx) {
    second.trace_backward(p, first.out, &first.d_out, first.out.shape);
    first.trace_backward(p, x, dx, x.shape);
  }
  const Ref& out() const { return second.out; }
  Ref& d_out() { return second.d_out; }
  void forward(Backend& be, ParameterSet& ps, const Ref& x, bool training) {
    first.forward(be, ps, x, training);
    second.forward(be, ps, first.out, training);
  }
  void backward(Backend& be, ParameterSet& ps, const Ref& x, Ref* dx) {
    second.backward(be, ps, first.out, &first.d_out);
    first.backward(be, ps, x, dx);
  }
};

// MaxPool 2x2 -> DoubleConv.
struct Down {
  DoubleConv conv;
  int in = 0, out = 0;
  Ref pooled, d_pooled, d_x_part;
  IRef argmax;

  // container: see ConvBnRelu::trace_forward (for the block's output).
  void trace_forward(TensorPlan& p, const Ref& x, Ref* container = nullptr,
                     Shape container_shape = {}) {
    const int64_t batch = x.dim(0), h = x.dim(2) / 2, w = x.dim(3) / 2;
    p.use(x);
    p.add(pooled, {batch, in, h, w});
    p.add(argmax, {batch, in, h, w});
    p.next();
    conv.trace_forward(p, pooled, static_cast<int>(batch), static_cast<int>(h), static_cast<int>(w),
                       container, std::move(container_shape));
  }
  // The block's output gradient written by an earlier step; dx (the input's) too.
  void trace_backward(TensorPlan& p, const Ref& dx) {
    conv.trace_backward(p, pooled, &d_pooled);
    p.use(d_pooled), p.use(argmax);
    p.add(d_x_part, dx.shape);
    p.next();
    p.use(dx), p.use(d_x_part);
    p.next();
  }
  void forward(Backend& be, ParameterSet& ps, const Ref& x, bool training) {
    be.maxpool2x2_forward(x, pooled, argmax);
    conv.forward(be, ps, pooled, training);
  }
  // d_out of conv filled by the consumer; adds this block's gradient into dx.
  void backward(Backend& be, ParameterSet& ps, Ref& dx) {
    conv.backward(be, ps, pooled, &d_pooled);
    be.maxpool2x2_backward(d_pooled, argmax, d_x_part);
    be.add_inplace(dx, d_x_part);
  }
};

// Upsample (bilinear x2 or ConvTranspose 2x2/2) -> pad to the skip -> [skip, up] -> DoubleConv.
struct Up {
  DoubleConv conv;
  bool transposed = false;
  ConvParams up;  // transposed only: weight (in, in/2, 2, 2), bias (in/2)
  int in = 0, up_channels = 0, skip_channels = 0;
  Ref upsampled, d_upsampled, cat, d_cat;
  // Eval with batch 1 and no padding: `upsampled` is the band of `cat` after the skip, so the
  // upsampling writes its part of the concatenation in place.
  bool upsampled_in_cat = false;
  // Training with batch 1 and no padding: the skip (the encoder block's output) is the leading
  // band of `cat`, written there by that block (`cat` added by its trace), so the concatenation
  // copies only the upsampled part and the skip is not kept twice.
  bool skip_in_cat = false;

  // The training forward's steps: upsample (dead once concatenated: the backward reads only
  // the block's input), concatenate, DoubleConv.
  void trace_forward(TensorPlan& p, const Ref& x, const Ref& skip) {
    const int64_t batch = x.dim(0), skip_h = skip.dim(2), skip_w = skip.dim(3);
    upsampled_in_cat = false;
    p.use(x);
    p.add(upsampled, {batch, up_channels, 2 * x.dim(2), 2 * x.dim(3)});
    p.next();
    p.use(skip), p.use(upsampled);
    if (skip_in_cat) {
      p.use(cat);
    } else {
      p.add(cat, {batch, skip_channels + up_channels, skip_h, skip_w});
    }
    p.next();
    conv.trace_forward(p, cat, static_cast<int>(batch), static_cast<int>(skip_h), static_cast<int>(skip_w));
  }
  // The backward's steps, the block's output gradient written by an earlier step; d_skip and
  // dx (new tensors) are the skip's and the input's gradients.
  void trace_backward(TensorPlan& p, const Ref& x, const Ref& skip, Ref& d_skip, Ref& dx) {
    conv.trace_backward(p, cat, &d_cat);
    p.use(d_cat);
    p.add(d_skip, skip.shape);
    p.add(d_upsampled, upsampled.shape);
    p.next();
    p.use(d_upsampled);
    if (transposed) p.use(x);
    p.add(dx, x.shape);
    p.next();
  }
  void forward(Backend& be, ParameterSet& ps, const Ref& x, const Ref& skip, bool training) {
    if (transposed) {
      Ref bias = ps.value(up.bias);
      be.conv_transpose2d_forward(x, ps.value(up.weight), &bias, upsampled);
    } else {
      be.upsample2x_forward(x, upsampled);
    }
    if (upsampled_in_cat) {
      be.copy_channels(skip, 0, cat);
    } else if (skip_in_cat) {
      be.copy_channels(upsampled, skip_channels, cat);
    } else {
      be.pad_concat_forward(skip, upsampled, cat);
    }
    conv.forward(be, ps, cat, training);
  }
  // Writes d_skip and dx (both overwritten).
  void backward(Backend& be, ParameterSet& ps, const Ref& x, Ref& d_skip, Ref& dx) {
    conv.backward(be, ps, cat, &d_cat);
    be.pad_concat_backward(d_cat, d_skip, d_upsampled);
    if (transposed) {
      Ref dw = ps.grad(up.weight), db = ps.grad(up.bias);
      be.conv_transpose2d_backward(x, ps.value(up.weight), d_upsampled, dx, dw, &db);
    } else {
      be.upsample2x_backward(d_upsampled, dx);
    }
  }
};

}  // namespace

struct PillarSegNet::Impl {
  // Pillar stream.
  int pfn_weight = -1;
  BnParams pfn_bn;
  Ref pillar_points, pfn_dpoints, pfn_out, pfn_dout;
  IRef pillar_cells, pfn_argmax;
  int64_t pillar_capacity = -1, num_pillars = 0;
  // The PFN's training scratch (Backend::pfn_forward), (capacity, N, C) and (2, capacity, N, C),
  // in the training plan where little else is alive; planned for this pillar capacity.
  Ref pfn_forward_scratch, pfn_backward_scratch;
  int64_t training_pillar_capacity = -1;
  // Occupancy stream.
  ConvBnRelu occupancy;
  Ref occupancy_input;
  // Grid-map input.
  Ref grid_map_input;
  // U-Net.
  std::vector<Down> downs;
  std::vector<Up> ups;
  ConvParams head;
  std::vector<Ref> x, dx;  // x[0] input canvas, x[i] output of down i
  Ref logits, d_logits, coefficients;
  LRef labels, predicted;
  Ref probs;
  int planned_batch = -1;
  bool planned_training = false;
  // Both plans overlay tensors by lifetime; the training plan's backward overwrites d_logits, so
  // each backward needs a loss() of its own.
  size_t training_bytes = 0, eval_bytes = 0;
  bool loss_gradient_ready = false;
  int training_batch = -1, eval_batch = -1;

  std::unique_ptr<Arena> activations, eval_activations, pillars;
  int64_t memory_generation = 0;  // incremented whenever an arena is (re)allocated

  // Every BatchNorm of the network (pointers into the members above, fixed after construction).
  std::vector<BnParams*> batchnorms() {
    std::vector<BnParams*> all;
    if (pfn_weight >= 0) all.push_back(&pfn_bn);
    if (occupancy.conv.weight >= 0) all.push_back(&occupancy.bn);
    for (Down& d : downs) all.insert(all.end(), {&d.conv.first.bn, &d.conv.second.bn});
    for (Up& u : ups) all.insert(all.end(), {&u.conv.first.bn, &u.conv.second.bn});
    return all;
  }

  // The evaluation forward recorded as a graph (backends with supports_capture()), valid until
  // the next re-plan; cells (capacity, 3) of -1, the padding rows' cells (outside every canvas).
  std::unique_ptr<CapturedGraph> eval_graph;
  std::vector<int32_t> padding_cells;
};

PillarSegNet::PillarSegNet(const ModelConfig& config, Backend& backend, uint64_t seed)
    : config_(config), backend_(backend), params_(backend), impl_(std::make_unique<Impl>()) {
  config_.validate();
  Impl& m = *impl_;
  ParameterSet& ps = params_;
  const int C = config_.pillar_channels, b = config_.base_width, depth = config_.depth;
  if (config_.pillar_input) {
    m.pfn_weight = ps.add_trainable("vfe.pfn_layers.0.linear.weight", {C, 10}, 10);
    m.pfn_bn = declare_bn(ps, "vfe.pfn_layers.0.norm", C, 1e-3f, 0.01f);
  }
  if (config_.occupancy != OccupancyInput::None) {
    m.occupancy.conv =
        declare_conv(ps, "occupancy.conv", config_.occupancy_input_channels(), config_.occupancy_channels, 3, false);
    m.occupancy.bn = declare_bn(ps, "occupancy.norm", config_.occupancy_channels, 1e-3f, 0.01f);
  }
  // Channel counts: c[0] = I; bilinear: c[i] = b * 2^i for i < depth, c[depth] = c[depth-1]
  // (milesial's factor 2); transposed: c[i] = b * 2^i for every i.
  std::vector<int> c(static_cast<size_t>(depth) + 1);
  c[0] = config_.input_channels();
  for (int i = 1; i <= depth; ++i) c[i] = b << i;
  if (!config_.transposed && depth >= 2) c[depth] = c[depth - 1];
  if (!config_.transposed && depth == 1) c[1] = b;
  for (int i = 1; i <= depth; ++i) {
    Down d;
    d.in = c[i - 1], d.out = c[i];
    d.conv = DoubleConv::declare(ps, fmt::format("segmentation_head.down{}.maxpool_conv.1", i), d.in, d.out, d.out);
    m.downs.push_back(std::move(d));
  }
  int current = c[depth];
  for (int j = 1; j <= depth; ++j) {
    const int skip_level = depth - j;
    Up u;
    u.transposed = config_.transposed;
    u.in = current;
    u.skip_channels = c[skip_level];
    const std::string prefix = fmt::format("segmentation_head.up{}", j);
    if (config_.transposed) {
      u.up_channels = current / 2;
      u.up.in = current, u.up.out = current / 2, u.up.k = 2, u.up.pad = 0;
      // PyTorch's fan_in of a ConvTranspose weight (in, out, k, k) is out * k * k.
      u.up.weight = ps.add_trainable(prefix + ".up.weight", {current, current / 2, 2, 2}, int64_t{current / 2} * 4);
      u.up.bias = ps.add_trainable(prefix + ".up.bias", {current / 2}, int64_t{current / 2} * 4);
    } else {
      u.up_channels = current;
    }
    const int cat = u.skip_channels + u.up_channels;
    const int out = skip_level == 0 ? b : (config_.transposed ? c[skip_level] : c[skip_level] / 2);
    const int mid = config_.transposed ? out : cat / 2;
    u.conv = DoubleConv::declare(ps, prefix + ".conv", cat, out, mid);
    current = out;
    m.ups.push_back(std::move(u));
  }
  m.head = declare_conv(ps, "segmentation_head.outc.conv", current, config_.num_classes, 1, true);
  params_.finalize(seed);
  m.activations = std::make_unique<Arena>(backend_);
  m.eval_activations = std::make_unique<Arena>(backend_);
  m.pillars = std::make_unique<Arena>(backend_);
}

PillarSegNet::~PillarSegNet() = default;

void PillarSegNet::set_batchnorm_momentum(float momentum) {
  PS_CHECK(momentum <= 1, "BatchNorm momentum must be at most 1, got {}", momentum);
  for (BnParams* bn : impl_->batchnorms()) bn->momentum = momentum > 0 ? momentum : bn->module_momentum;
}

void PillarSegNet::plan(int batch, bool training) {
  Impl& m = *impl_;
  // The training plan holds the PFN's scratch, sized by the pillar capacity.
  const bool same_capacity =
      !training || !config_.pillar_input || m.training_pillar_capacity == m.pillar_capacity;
  if (m.planned_batch == batch && m.planned_training == training && same_capacity) return;
  if (training) {
    plan_training(batch);
  } else {
    plan_eval(batch);
  }
  m.planned_batch = batch;
  m.planned_training = training;
  logits_ = m.logits;
}

// The training step's tensors by lifetime (TensorPlan): a forward activation that the backward
// reads lives until that read, one it does not read (the canvas, the upsampled tensors) until
// its last forward reader, and a gradient from the step that writes it to the one that consumes
// it. The outputs (logits, probabilities, labels) live until the next forward.
void PillarSegNet::plan_training(int batch) {
  Impl& m = *impl_;
  const int H = config_.grid.height(), W = config_.grid.width(), depth = config_.depth;
  TensorPlan p;
  m.x.assign(static_cast<size_t>(depth) + 1, Ref{});
  m.dx.assign(static_cast<size_t>(depth) + 1, Ref{});
  Ref& canvas = m.x[0];
  Ref& d_canvas = m.dx[0];
  // The level-i output x[i] (i >= 1) is down i's block output, and its gradient dx[i] that
  // block's output gradient: the trace names those members, the vectors get copies after bind().
  const auto level_out = [&](int i) -> const Ref& {
    return i == 0 ? canvas : m.downs[static_cast<size_t>(i - 1)].conv.out();
  };
  const auto level_grad = [&](int i) -> Ref& {
    return i == 0 ? d_canvas : m.downs[static_cast<size_t>(i - 1)].conv.d_out();
  };

  // Forward: uploads and the pillar stream into the canvas, then the other input streams.
  const int64_t N = config_.max_points_per_pillar, C = config_.pillar_channels;
  p.add(canvas, {batch, config_.input_channels(), H, W});
  if (config_.pillar_input) p.add(m.pfn_forward_scratch, {m.pillar_capacity, N, C});
  if (config_.occupancy != OccupancyInput::None)
    p.add(m.occupancy_input, {batch, config_.occupancy_input_channels(), H, W});
  if (config_.grid_map_input) p.add(m.grid_map_input, {batch, 6, H, W});
  p.next();
  if (config_.occupancy != OccupancyInput::None) {
    m.occupancy.trace_forward(p, m.occupancy_input, batch, H, W);
    p.use(m.occupancy.out), p.use(canvas);
    p.next();
  }
  if (config_.grid_map_input) {
    p.use(m.grid_map_input), p.use(canvas);
    p.next();
  }
  // Level i's size; with batch 1, an Up whose upsampled input has its skip's size (no padding)
  // takes the skip in its concatenation buffer (Up::skip_in_cat). The canvas (level 0) stays
  // apart: it is dead before the backward, where the concatenation would have to outlive it.
  std::vector<int64_t> hs(static_cast<size_t>(depth) + 1, H), ws(static_cast<size_t>(depth) + 1, W);
  for (int i = 1; i <= depth; ++i) hs[static_cast<size_t>(i)] = hs[static_cast<size_t>(i - 1)] / 2;
  for (int i = 1; i <= depth; ++i) ws[static_cast<size_t>(i)] = ws[static_cast<size_t>(i - 1)] / 2;
  for (Up& u : m.ups) u.skip_in_cat = false;
  for (int i = 1; i <= depth; ++i) {
    const size_t level = static_cast<size_t>(i);
    Ref* container = nullptr;
    Shape container_shape;
    if (i < depth && batch == 1 && 2 * hs[level + 1] == hs[level] &&
        2 * ws[level + 1] == ws[level]) {
      // Up depth - i takes level i's skip.
      Up& consumer = m.ups[static_cast<size_t>(depth - i - 1)];
      consumer.skip_in_cat = true;
      container = &consumer.cat;
      container_shape = {batch, consumer.skip_channels + consumer.up_channels, hs[level],
                         ws[level]};
    }
    m.downs[static_cast<size_t>(i - 1)].trace_forward(p, level_out(i - 1), container,
                                                      std::move(container_shape));
  }
  const Ref* current = &level_out(depth);
  for (int j = 1; j <= depth; ++j) {
    Up& u = m.ups[static_cast<size_t>(j - 1)];
    u.trace_forward(p, *current, level_out(depth - j));
    current = &u.conv.out();
  }
  p.use(*current);
  p.add(m.logits, {batch, config_.num_classes, H, W});
  p.add(m.probs, {batch, config_.num_classes, H, W});
  p.add(m.predicted, {batch, H, W});
  p.keep(m.logits), p.keep(m.probs), p.keep(m.predicted);
  p.next();
  // Loss.
  p.use(m.logits);
  p.add(m.labels, {batch, H, W});
  p.add(m.coefficients, {13});
  p.add(m.d_logits, {batch, config_.num_classes, H, W});
  p.keep(m.labels), p.keep(m.coefficients);
  p.next();
  // Backward, in backward()'s order.
  Up& last = m.ups.back();
  p.use(last.conv.out()), p.use(m.d_logits);
  p.add(last.conv.d_out(), last.conv.out().shape);
  p.next();
  for (int j = depth; j >= 1; --j) {
    Up& u = m.ups[static_cast<size_t>(j - 1)];
    const Ref& input = j == 1 ? level_out(depth) : m.ups[static_cast<size_t>(j - 2)].conv.out();
    Ref& d_input = j == 1 ? level_grad(depth) : m.ups[static_cast<size_t>(j - 2)].conv.d_out();
    u.trace_backward(p, input, level_out(depth - j), level_grad(depth - j), d_input);
  }
  for (int i = depth; i >= 1; --i) m.downs[static_cast<size_t>(i - 1)].trace_backward(p, level_grad(i - 1));
  p.use(d_canvas);  // the scatter's backward, then the PFN's
  if (config_.pillar_input) p.add(m.pfn_backward_scratch, {2, m.pillar_capacity, N, C});
  p.next();
  if (config_.occupancy != OccupancyInput::None) {
    p.use(d_canvas);
    p.add(m.occupancy.d_out, m.occupancy.out.shape);
    p.next();
    m.occupancy.trace_backward(p, m.occupancy_input, nullptr, {});
  }

  const size_t bytes = p.plan();
  Arena& a = *m.activations;
  // Kept while the batch size stays, so that switching between training and eval does not
  // allocate.
  if (m.training_batch != batch) a.release();
  a.reserve(bytes);
  a.reset();
  p.bind(a.take<uint8_t>({static_cast<int64_t>(bytes)}).data);
  ++m.memory_generation;  // every Ref of the plan may have moved
  for (int i = 1; i <= depth; ++i) {
    m.x[static_cast<size_t>(i)] = level_out(i);
    m.dx[static_cast<size_t>(i)] = level_grad(i);
  }
  m.training_batch = batch;
  m.training_bytes = bytes;
  m.training_pillar_capacity = m.pillar_capacity;
}

// The eval forward's tensors in the order it runs, each with the steps that read or write it;
// the planner overlays those whose lifetimes are disjoint. Eval needs no conv_out (Conv, BN and
// ReLU run as one op) and no gradients; the training-only Refs stay null.
void PillarSegNet::plan_eval(int batch) {
  Impl& m = *impl_;
  const int H = config_.grid.height(), W = config_.grid.width(), depth = config_.depth;
  constexpr int kEnd = 1 << 30;  // alive until the next forward
  LifetimePlanner planner;
  std::vector<std::pair<float**, int>> float_slots;
  std::vector<std::tuple<float**, int, size_t>> band_slots;  // a Ref inside another, at a byte offset
  std::vector<std::pair<int32_t**, int>> int_slots;
  std::vector<std::pair<uint8_t**, int>> label_slots;
  const auto place = [&](Ref& r, Shape shape, int first, int last) {
    r = Ref{nullptr, std::move(shape)};
    const int id = planner.add(r.bytes(), first, last);
    float_slots.push_back({&r.data, id});
    return id;
  };
  for (Down& d : m.downs) d.conv.first.conv_out = d.conv.second.conv_out = Ref{};
  for (Up& u : m.ups) {
    u.conv.first.conv_out = u.conv.second.conv_out = Ref{};
    u.skip_in_cat = false;
  }
  m.occupancy.conv_out = Ref{};
  m.dx.assign(static_cast<size_t>(depth) + 1, Ref{});
  m.x.assign(static_cast<size_t>(depth) + 1, Ref{});

  int step = 0;
  std::vector<int> x_ids(static_cast<size_t>(depth) + 1);
  std::vector<int> hs(static_cast<size_t>(depth) + 1), ws(static_cast<size_t>(depth) + 1);
  hs[0] = H, ws[0] = W;
  x_ids[0] = place(m.x[0], {batch, config_.input_channels(), H, W}, step, step);
  if (config_.occupancy != OccupancyInput::None) {
    place(m.occupancy_input, {batch, config_.occupancy_input_channels(), H, W}, step, step + 1);
    place(m.occupancy.out, {batch, config_.occupancy_channels, H, W}, step + 1, step + 2);
    step += 2;
  }
  if (config_.grid_map_input) {
    place(m.grid_map_input, {batch, 6, H, W}, step, step + 1);
    step += 1;
  }
  for (int i = 1; i <= depth; ++i) {
    Down& d = m.downs[static_cast<size_t>(i - 1)];
    const int h = hs[i - 1] / 2, w = ws[i - 1] / 2;
    planner.use_until(x_ids[static_cast<size_t>(i - 1)], step + 1);
    place(d.pooled, {batch, d.in, h, w}, step + 1, step + 2);
    d.argmax = IRef{nullptr, {batch, d.in, h, w}};
    int_slots.push_back({&d.argmax.data, planner.add(d.argmax.bytes(), step + 1, step + 1)});
    place(d.conv.first.out, {batch, d.conv.first.conv.out, h, w}, step + 2, step + 3);
    x_ids[static_cast<size_t>(i)] = place(d.conv.second.out, {batch, d.out, h, w}, step + 3, step + 3);
    m.x[static_cast<size_t>(i)] = d.conv.second.out;
    hs[i] = h, ws[i] = w;
    step += 3;
  }
  int current = x_ids[static_cast<size_t>(depth)];
  int h = hs[depth], w = ws[depth];
  for (int j = 1; j <= depth; ++j) {
    Up& u = m.ups[static_cast<size_t>(j - 1)];
    const int skip = depth - j;
    planner.use_until(current, step + 1);
    u.upsampled_in_cat = batch == 1 && 2 * h == hs[skip] && 2 * w == ws[skip];
    planner.use_until(x_ids[static_cast<size_t>(skip)], step + 2);
    if (u.upsampled_in_cat) {
      const int cat_id = place(u.cat, {batch, u.skip_channels + u.up_channels, hs[skip], ws[skip]}, step + 1, step + 3);
      u.upsampled = Ref{nullptr, {batch, u.up_channels, 2 * h, 2 * w}};
      const size_t skip_bytes = static_cast<size_t>(u.skip_channels) * hs[skip] * ws[skip] * sizeof(float);
      band_slots.push_back({&u.upsampled.data, cat_id, skip_bytes});
    } else {
      place(u.upsampled, {batch, u.up_channels, 2 * h, 2 * w}, step + 1, step + 2);
      place(u.cat, {batch, u.skip_channels + u.up_channels, hs[skip], ws[skip]}, step + 2, step + 3);
    }
    place(u.conv.first.out, {batch, u.conv.first.conv.out, hs[skip], ws[skip]}, step + 3, step + 4);
    current = place(u.conv.second.out, {batch, u.conv.second.conv.out, hs[skip], ws[skip]}, step + 4, step + 4);
    h = hs[skip], w = ws[skip];
    step += 4;
  }
  planner.use_until(current, step + 1);
  place(m.logits, {batch, config_.num_classes, H, W}, step + 1, kEnd);
  place(m.d_logits, {batch, config_.num_classes, H, W}, step + 1, kEnd);
  place(m.probs, {batch, config_.num_classes, H, W}, step + 1, kEnd);
  place(m.coefficients, {13}, step + 1, kEnd);
  for (LRef* r : {&m.labels, &m.predicted}) {
    *r = LRef{nullptr, {batch, H, W}};
    label_slots.push_back({&r->data, planner.add(r->bytes(), step + 1, kEnd)});
  }

  const size_t bytes = planner.plan();
  Arena& a = *m.eval_activations;
  // The same batch size gives the same plan in the same block: a recorded graph stays valid
  // across switches between training and eval; another batch size records again.
  if (m.eval_batch != batch) {
    a.release();
    m.eval_graph.reset();
  }
  a.reserve(bytes);
  ++m.memory_generation;  // every Ref of the plan may have moved
  a.reset();
  uint8_t* base = a.take<uint8_t>({static_cast<int64_t>(bytes)}).data;
  for (auto& [ptr, id] : float_slots) *ptr = reinterpret_cast<float*>(base + planner.offset(id));
  for (auto& [ptr, id, bytes_in] : band_slots) *ptr = reinterpret_cast<float*>(base + planner.offset(id) + bytes_in);
  for (auto& [ptr, id] : int_slots) *ptr = reinterpret_cast<int32_t*>(base + planner.offset(id));
  for (auto& [ptr, id] : label_slots) *ptr = base + planner.offset(id);
  // The Refs copied before their data pointers were set.
  for (int i = 1; i <= depth; ++i) m.x[static_cast<size_t>(i)] = m.downs[static_cast<size_t>(i - 1)].conv.second.out;
  m.eval_batch = batch;
  m.eval_bytes = bytes;
}

void PillarSegNet::plan_pillars(int64_t pillars, bool at_capacity) {
  Impl& m = *impl_;
  const int N = config_.max_points_per_pillar, C = config_.pillar_channels;
  if (pillars > m.pillar_capacity) {
    m.eval_graph.reset();  // it names the old buffers
    // Grow with headroom so that a slowly rising pillar count does not re-plan every batch.
    const int64_t capacity = std::max<int64_t>(pillars + pillars / 4, 1024);
    Arena& a = *m.pillars;
    a.release();
    a.begin_measure();
    for (int pass = 0; pass < 2; ++pass) {
      if (pass == 1) {
        a.reserve(a.used());
        a.reset();
      }
      a.take<float>({capacity, N, 10});
      a.take<int32_t>({capacity, 3});
      a.take<float>({capacity, N, 10});
      a.take<int32_t>({capacity, C});
      a.take<float>({capacity, C});
      a.take<float>({capacity, C});
      a.take<float>({C});
      a.take<float>({C});
    }
    m.pillar_capacity = capacity;
    m.padding_cells.assign(static_cast<size_t>(capacity) * 3, -1);
    ++m.memory_generation;
  }
  // Views of the current size (or of the whole capacity) at the start of each buffer.
  Arena& a = *m.pillars;
  a.reset();
  const int64_t cap = m.pillar_capacity, rows = at_capacity ? cap : pillars;
  const auto carve = [&](auto tag, Shape full, Shape used) {
    using T = decltype(tag);
    RefT<T> r = a.take<T>(std::move(full));
    r.shape = std::move(used);
    return r;
  };
  m.pillar_points = carve(float{}, {cap, N, 10}, {rows, N, 10});
  m.pillar_cells = carve(int32_t{}, {cap, 3}, {rows, 3});
  m.pfn_dpoints = carve(float{}, {cap, N, 10}, {rows, N, 10});
  m.pfn_argmax = carve(int32_t{}, {cap, C}, {rows, C});
  m.pfn_out = carve(float{}, {cap, C}, {rows, C});
  m.pfn_dout = carve(float{}, {cap, C}, {rows, C});
  m.pfn_bn.save_mean = a.take<float>({C});
  m.pfn_bn.save_invstd = a.take<float>({C});
  m.num_pillars = pillars;
}

size_t PillarSegNet::activation_bytes() const {
  const Impl& m = *impl_;
  return (m.planned_training ? m.training_bytes : m.eval_bytes) + m.pillars->used();
}

PillarSegNet::Inputs PillarSegNet::prepare(int batch, int64_t pillar_rows, bool training) {
  Impl& m = *impl_;
  PS_CHECK(batch >= 1, "prepare: batch size must be >= 1, got {}", batch);
  PS_CHECK(pillar_rows >= 0, "prepare: pillar rows must be >= 0, got {}", pillar_rows);
  if (config_.pillar_input) plan_pillars(pillar_rows, /*at_capacity=*/false);
  plan(batch, training);  // after plan_pillars: the training plan needs the pillar capacity
  Inputs in;
  if (config_.pillar_input) {
    in.pillar_points = m.pillar_points;
    in.pillar_cells = m.pillar_cells;
  }
  in.occupancy = m.occupancy_input;
  in.grid_map = m.grid_map_input;
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
  // timing, which waits between stages, is off). The graph runs the pillar stream at the pillar
  // capacity: rows past this batch's P hold zero points and cells (-1, -1, -1), which the scatter
  // skips, so one recording serves every pillar count up to the capacity, the count itself never
  // reaching the device work; a re-plan (another batch size, more pillars than the capacity)
  // records again.
  const bool replay = !training && !time_stages_ && be.supports_capture();

  // Inputs: checked, then uploaded.
  if (config_.pillar_input) {
    const int64_t P = batch.pillar_points.rank() == 3 ? batch.pillar_points.dim(0) : 0;
    PS_CHECK(batch.pillar_points.rank() == 3 || batch.pillar_points.numel() == 0,
             "forward: pillar_points must be (P, N, 10), got {}", shape_str(batch.pillar_points.shape()));
    if (P > 0) {
      PS_CHECK(batch.pillar_points.dim(1) == config_.max_points_per_pillar && batch.pillar_points.dim(2) == 10,
               "forward: pillar_points must be (P, {}, 10), got {}", config_.max_points_per_pillar,
               shape_str(batch.pillar_points.shape()));
      PS_CHECK(batch.pillar_cells.shape() == (Shape{P, 3}), "forward: pillar_cells must be ({}, 3), got {}", P,
               shape_str(batch.pillar_cells.shape()));
    }
    plan_pillars(P, replay);
    const size_t point_bytes = static_cast<size_t>(P) * static_cast<size_t>(config_.max_points_per_pillar) * 10 *
                               sizeof(float);
    const size_t cell_bytes = static_cast<size_t>(P) * 3 * sizeof(int32_t);
    if (P > 0) {
      be.upload(m.pillar_points.data, batch.pillar_points.data(), point_bytes);
      be.upload(m.pillar_cells.data, batch.pillar_cells.data(), cell_bytes);
    }
    if (replay) {
      be.fill_zero(reinterpret_cast<char*>(m.pillar_points.data) + point_bytes, m.pillar_points.bytes() - point_bytes);
      be.upload(reinterpret_cast<char*>(m.pillar_cells.data) + cell_bytes, m.padding_cells.data(),
                m.pillar_cells.bytes() - cell_bytes);
    }
  }
  plan(batch.batch, training);  // after plan_pillars: the training plan needs the pillar capacity
  if (config_.occupancy != OccupancyInput::None) {
    const Shape expected{batch.batch, config_.occupancy_input_channels(), H, W};
    PS_CHECK(batch.occupancy.shape() == expected, "forward: occupancy input must be {}, got {}", shape_str(expected),
             shape_str(batch.occupancy.shape()));
    be.upload(m.occupancy_input.data, batch.occupancy.data(), m.occupancy_input.bytes());
  }
  if (config_.grid_map_input) {
    const Shape expected{batch.batch, 6, H, W};
    PS_CHECK(batch.grid_map.shape() == expected, "forward: grid_map input must be {}, got {}", shape_str(expected),
             shape_str(batch.grid_map.shape()));
    be.upload(m.grid_map_input.data, batch.grid_map.data(), m.grid_map_input.bytes());
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
  if (!m.eval_graph || !m.eval_graph->valid()) m.eval_graph = be.capture([&] { run(false); });
  m.eval_graph->replay();
}

// The device work of a forward: canvas, input streams, U-Net, head.
void PillarSegNet::run(bool training) {
  Impl& m = *impl_;
  Backend& be = backend_;
  ParameterSet& ps = params_;
  PS_CHECK(m.planned_batch > 0 && m.planned_training == training,
           "PillarSegNet::run({}): plan the inputs first (prepare() or forward())",
           training ? "training" : "eval");
  // Stage clock: with timing on, each call closes the stage that ran since the previous one.
  stage_times_ = StageTimes{};
  m.loss_gradient_ready = false;
  double last = time_stages_ ? be.clock_ms() : 0.0;
  run_started_ms_ = last;
  const auto lap = [&](double& stage) {
    if (!time_stages_) return;
    const double now = be.clock_ms();
    stage = now - last;
    last = now;
  };
  Ref& canvas = m.x[0];
  be.fill_zero(canvas.data, canvas.bytes());
  int channel = 0;
  if (config_.pillar_input) {
    if (m.pillar_points.dim(0) > 0) {
      BatchNormRefs r = bn_refs(ps, m.pfn_bn);
      be.pfn_forward(m.pillar_points, ps.value(m.pfn_weight), r, training, m.pfn_argmax, m.pfn_out,
                     training ? m.pfn_forward_scratch : Ref{});
      if (training) ps.counters()[m.pfn_bn.counter] += 1;
      lap(stage_times_.pfn);
      be.scatter_forward(m.pfn_out, m.pillar_cells, 0, canvas);
      lap(stage_times_.scatter);
    }
    channel += config_.pillar_channels;
  }
  if (config_.occupancy != OccupancyInput::None) {
    m.occupancy.forward(be, ps, m.occupancy_input, training);
    be.copy_channels(m.occupancy.out, channel, canvas);
    channel += config_.occupancy_channels;
    lap(stage_times_.occupancy);
  }
  if (config_.grid_map_input) be.copy_channels(m.grid_map_input, channel, canvas);
  const int depth = config_.depth;
  for (int i = 1; i <= depth; ++i) m.downs[static_cast<size_t>(i - 1)].forward(be, ps, m.x[i - 1], training);
  Ref current = m.x[depth];
  for (int j = 1; j <= depth; ++j) {
    Up& u = m.ups[static_cast<size_t>(j - 1)];
    u.forward(be, ps, current, m.x[depth - j], training);
    current = u.conv.out();
  }
  lap(stage_times_.unet);
  Ref head_bias = ps.value(m.head.bias);
  be.conv2d_forward(current, ps.value(m.head.weight), &head_bias, 0, m.logits);
  lap(stage_times_.head);
}

void PillarSegNet::queue_predictions(bool probabilities) {
  Impl& m = *impl_;
  PS_CHECK(m.planned_batch > 0, "queue_predictions() before a forward");
  backend_.argmax(m.logits, m.predicted);
  if (probabilities) backend_.softmax(m.logits, m.probs);
}

const LRef& PillarSegNet::predicted() const { return impl_->predicted; }
const Ref& PillarSegNet::probs() const { return impl_->probs; }

double PillarSegNet::loss(const Tensor<uint8_t>& labels, LossKind kind, const std::array<float, 13>& coefficients) {
  Impl& m = *impl_;
  PS_CHECK(m.planned_batch > 0, "loss() before forward()");
  const Shape expected{m.planned_batch, config_.grid.height(), config_.grid.width()};
  PS_CHECK(labels.shape() == expected, "loss: labels must be {}, got {}", shape_str(expected), shape_str(labels.shape()));
  backend_.upload(m.labels.data, labels.data(), m.labels.bytes());
  backend_.upload(m.coefficients.data, coefficients.data(), m.coefficients.bytes());
  const double value = backend_.loss(kind, m.logits, m.labels, m.coefficients, m.d_logits);
  m.loss_gradient_ready = true;
  return value;
}

void PillarSegNet::backward() {
  Impl& m = *impl_;
  PS_CHECK(m.planned_training, "backward() needs a training-mode forward first (the eval forward keeps no "
                               "activations for it)");
  PS_CHECK(m.loss_gradient_ready, "backward() needs loss() after the training forward (each backward consumes "
                                  "the logits' gradient that loss() writes)");
  m.loss_gradient_ready = false;
  Backend& be = backend_;
  ParameterSet& ps = params_;
  const int depth = config_.depth;
  Up& last = m.ups.back();
  Ref dw = ps.grad(m.head.weight), db = ps.grad(m.head.bias);
  be.conv2d_backward(last.conv.out(), ps.value(m.head.weight), m.d_logits, 0, &last.conv.d_out(), dw, &db);
  for (int j = depth; j >= 1; --j) {
    Up& u = m.ups[static_cast<size_t>(j - 1)];
    const Ref& input = j == 1 ? m.x[depth] : m.ups[static_cast<size_t>(j - 2)].conv.out();
    Ref& d_input = j == 1 ? m.dx[depth] : m.ups[static_cast<size_t>(j - 2)].conv.d_out();
    u.backward(be, ps, input, m.dx[depth - j], d_input);
  }
  for (int i = depth; i >= 1; --i) {
    // dx[i] (the block's d_out) is complete: the Up's skip gradient plus block i+1's part.
    m.downs[static_cast<size_t>(i - 1)].backward(be, ps, m.dx[i - 1]);
  }
  int channel = 0;
  if (config_.pillar_input) {
    if (m.num_pillars > 0) {
      be.scatter_backward(m.dx[0], m.pillar_cells, 0, m.pfn_dout);
      const BatchNormRefs r = bn_refs(ps, m.pfn_bn);
      Ref dweight = ps.grad(m.pfn_weight), dgamma = ps.grad(m.pfn_bn.gamma), dbeta = ps.grad(m.pfn_bn.beta);
      be.pfn_backward(m.pillar_points, ps.value(m.pfn_weight), r, m.pfn_argmax, m.pfn_dout,
                      m.pfn_dpoints, dweight, dgamma, dbeta, m.pfn_backward_scratch);
    } else {
      for (int idx : {m.pfn_weight, m.pfn_bn.gamma, m.pfn_bn.beta}) {
        Ref g = ps.grad(idx);
        be.fill_zero(g.data, g.bytes());
      }
    }
    channel += config_.pillar_channels;
  }
  if (config_.occupancy != OccupancyInput::None) {
    be.extract_channels(m.dx[0], channel, m.occupancy.d_out);
    m.occupancy.backward(be, ps, m.occupancy_input, nullptr);
  }
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
