// PillarSegNet as two op graphs (engine/model/graph.hpp): the evaluation forward, and the
// training step (forward, loss, backward). build_graph() emits every node in the order the
// backend runs it, the graph's lifetime planner places the activations of each in one block,
// and execute() runs a range of nodes on the backend. The modules below only declare the
// parameters (in the order of the PyTorch state_dict, which the seeded initialisation follows).
#include "engine/model/pillarsegnet.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <initializer_list>
#include <string>
#include <utility>
#include <vector>

#include "core/error.hpp"
#include "core/ops.hpp"
#include "engine/model/graph.hpp"
#include "engine/model/memory_estimate.hpp"

namespace pillarseg {

namespace {

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
};

// Conv -> BatchNorm -> ReLU; bn indexes the model's BatchNorm table.
struct ConvBnRelu {
  ConvParams conv;
  int bn = -1;
};

// [Conv3x3 (bias) -> BN -> ReLU] x 2, PyTorch module `double_conv` (indices 0,1 and 3,4).
struct DoubleConv {
  ConvBnRelu first, second;
};

// MaxPool 2x2 -> DoubleConv.
struct Down {
  DoubleConv conv;
  int in = 0, out = 0;
};

// Upsample (bilinear x2 or ConvTranspose 2x2/2) -> pad to the skip -> [skip, up] -> DoubleConv.
struct Up {
  DoubleConv conv;
  bool transposed = false;
  ConvParams up;  // transposed only: weight (in, in/2, 2, 2), bias (in/2)
  int in = 0, up_channels = 0, skip_channels = 0;
};

}  // namespace

// One planned graph and its memory.
struct GraphPlan {
  Graph graph;
  size_t forward_end = 0;  // nodes [0, forward_end) are the forward, then the loss node
  size_t loss_node = 0;
  int batch = -1;
  int64_t pillar_capacity = -1;
  Precision precision = Precision::F32;  // of its 16-bit nodes
  std::unique_ptr<Arena> arena;
  uint8_t* base = nullptr;
  // Tensors the model binds outside the nodes.
  int pillar_points = -1, pillar_cells = -1, occupancy_input = -1, grid_map_input = -1;
  int logits = -1, d_logits = -1, probs = -1, labels = -1, coefficients = -1, predicted = -1;
  bool built() const { return batch > 0; }
};

struct PillarSegNet::Impl {
  int pfn_weight = -1, pfn_bn = -1;
  ConvBnRelu occupancy;  // conv.weight < 0 without the occupancy stream
  std::vector<Down> downs;
  std::vector<Up> ups;
  ConvParams head;
  std::vector<BnParams> bns;

  GraphPlan eval, train;
  GraphPlan* current = nullptr;
  LossKind loss_kind = LossKind::CrossEntropy;
  Precision precision = Precision::F32;        // of the evaluation convolutions
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

namespace {

// Emits the nodes of one graph in the order the backend runs them.
class Builder {
 public:
  // `precision`: the convolutions'; the evaluation forward also keeps the U-Net's activations in
  // it, training keeps them (and BatchNorm, the loss, gradients) in FP32.
  Builder(Graph& g, ParameterSet& ps, const Backend& backend, const std::vector<BnParams>& bns, bool training,
          Precision precision)
      : g_(g), ps_(ps), backend_(backend), bns_(bns), training_(training),
        half_(training ? Precision::F32 : precision), conv_precision_(precision) {}

  Stage stage = Stage::UNet;
  // 16-bit activations (the evaluation forward in bf16 / fp16).
  bool half() const { return half_ != Precision::F32; }
  // Convolutions on prepared 16-bit weights (the tensor-core kernels), in either graph.
  bool half_convs() const { return conv_precision_ != Precision::F32; }
  // The type of the U-Net's activations: 16-bit in a mixed-precision evaluation forward once
  // `unet` is set (the occupancy stream writes the FP32 canvas).
  bool unet = false;
  DType act() const { return half() && unet ? DType::U16 : DType::F32; }

  // Mixed precision: a node preparing the 16-bit weights (with the eval BatchNorm `bn` folded
  // in, when >= 0) and the tensor-core convolution x -> y.
  void half_conv(const std::string& name, int x, int w, int b, int bn, int pad, bool relu, int y) {
    const Shape w_shape = shape(w);
    const int w16 = g_.tensor(name + ".w16", op::half16_conv_weights(w_shape, false), DType::U16);
    const int b16 = g_.tensor(name + ".bias16", {w_shape[0]});
    // The backend's own transformed form of the weights, where it has one (the CPU's Winograd U).
    const int64_t transform = backend_.prepared_conv_transform_elements(w_shape, pad, conv_precision_);
    const int wt = transform > 0 ? g_.tensor(name + ".w16_transformed", {transform}, DType::U16) : -1;
    keep_prepared({w16, b16, wt});
    GraphNode& prep = node(OpKind::PrepareConvWeights, name, {w, b, w16, b16, wt}, {w, b}, {w16, b16, wt});
    prep.batchnorm = bn;
    GraphNode& n = node(OpKind::Conv2dHalf, name, {x, w16, b16, y, wt}, {x, w16, b16, wt}, {y});
    n.pad = pad;
    n.relu = relu;
    n.weight = w_shape;
    n.flops = op::conv2d_flops(shape(y), w_shape);
  }
  // The same for a transposed 2x2 convolution.
  void half_conv_transpose(const std::string& name, int x, int w, int b, int y) {
    const Shape w_shape = shape(w);
    const int w16 = g_.tensor(name + ".w16", op::half16_conv_weights(w_shape, true), DType::U16);
    const int b16 = g_.tensor(name + ".bias16", {4 * w_shape[1]});
    keep_prepared({w16, b16});
    node(OpKind::PrepareConvTransposeWeights, name, {w, b, w16, b16}, {w, b}, {w16, b16});
    GraphNode& n = node(OpKind::ConvTranspose2x2Half, name, {x, w16, b16, y}, {x, w16, b16}, {y});
    n.weight = w_shape;
    n.flops = op::conv_transpose2x2_flops(shape(x), w_shape);
  }

  // The evaluation forward's prepared weights persist from run to run (PillarSegNet::run prepares
  // them again only when the parameters changed); training prepares them every step.
  void keep_prepared(std::initializer_list<int> prepared) {
    if (training_) return;
    for (int id : prepared)
      if (id >= 0) g_.at(id).persistent = true;
  }

  int param(int index) { return index < 0 ? -1 : g_.parameter(index, ps_.entries()[static_cast<size_t>(index)].shape, false); }
  int grad(int index) { return index < 0 ? -1 : g_.parameter(index, ps_.entries()[static_cast<size_t>(index)].shape, true); }
  const Shape& shape(int id) const { return g_.at(id).shape; }

  GraphNode& node(OpKind op, std::string name, std::vector<int> args, std::vector<int> reads,
                  std::vector<int> writes) {
    GraphNode n;
    n.op = op;
    n.stage = stage;
    n.name = std::move(name);
    n.args = std::move(args);
    for (int id : reads)
      if (id >= 0) n.reads.push_back(id);
    for (int id : writes)
      if (id >= 0) n.writes.push_back(id);
    return g_.add(std::move(n));
  }

  // Conv2d (with its bias when it has one): x -> y, a new tensor named `out`.
  int conv(const std::string& name, const ConvParams& c, int x, const std::string& out) {
    const int w = param(c.weight), b = param(c.bias);
    const Shape b_shape = b >= 0 ? shape(b) : Shape{};
    const int y = g_.tensor(name + "." + out, op::conv2d(shape(x), shape(w), c.pad, b >= 0 ? &b_shape : nullptr));
    if (half_convs()) {
      half_conv(name, x, w, b, -1, c.pad, false, y);
      return y;
    }
    GraphNode& n = node(OpKind::Conv2d, name, {x, w, b, y}, {x, w, b}, {y});
    n.pad = c.pad;
    n.flops = op::conv2d_flops(shape(y), shape(w));
    return y;
  }
  // The two save-statistics tensors (C) of a training BatchNorm.
  std::pair<int, int> saved_stats(const std::string& name, int channels) {
    return {g_.tensor(name + ".save_mean", {channels}), g_.tensor(name + ".save_invstd", {channels})};
  }
  // BatchNorm + ReLU x -> y (training: batch statistics saved), y a new tensor or `into`.
  int bn_relu(const std::string& name, int bn, int x, int into = -1) {
    const int channels = static_cast<int>(shape(x)[1]);
    const int y = into >= 0 ? into : g_.tensor(name + ".out", op::batchnorm(shape(x), {channels}));
    int mean = -1, invstd = -1;
    if (training_) std::tie(mean, invstd) = saved_stats(name, channels);
    GraphNode& n = node(OpKind::BatchNormRelu, name, {x, y, mean, invstd}, {x}, {y, mean, invstd});
    n.batchnorm = bn;
    n.training = training_;
    return y;
  }
  // Conv -> BN -> ReLU: training two nodes (conv_out kept for the backward), eval one fused node.
  struct Activations {
    int conv_out = -1, out = -1, save_mean = -1, save_invstd = -1;
  };
  Activations conv_bn_relu(const std::string& name, const ConvBnRelu& m, int x, int into = -1) {
    Activations a;
    if (training_) {
      a.conv_out = conv(name, m.conv, x, "conv_out");
      a.out = bn_relu(name, m.bn, a.conv_out, into);
      const GraphNode& bn_node = g_.nodes().back();
      a.save_mean = bn_node.args[2], a.save_invstd = bn_node.args[3];
      return a;
    }
    const int w = param(m.conv.weight), b = param(m.conv.bias);
    const Shape b_shape = b >= 0 ? shape(b) : Shape{};
    const Shape y_shape = op::conv2d(shape(x), shape(w), m.conv.pad, b >= 0 ? &b_shape : nullptr);
    a.out = into >= 0 ? into : g_.tensor(name + ".out", y_shape, act());
    if (half()) {
      half_conv(name, x, w, b, m.bn, m.conv.pad, true, a.out);
      return a;
    }
    GraphNode& n = node(OpKind::Conv2dBnReluEval, name, {x, w, b, a.out}, {x, w, b}, {a.out});
    n.pad = m.conv.pad;
    n.batchnorm = m.bn;
    n.flops = op::conv2d_flops(y_shape, shape(w));
    return a;
  }
  // The backward of conv_bn_relu: d_out (written by the consumer) -> BN + ReLU backward in
  // place over d_out, then the conv backward into dx (a new tensor) when `with_dx`.
  int conv_bn_relu_backward(const std::string& name, const ConvBnRelu& m, int x, const Activations& a, int d_out,
                            bool with_dx, int dx = -1) {
    const int d_conv_out = g_.view(name + ".d_conv_out", d_out, shape(a.conv_out));
    GraphNode& bn = node(OpKind::BatchNormReluBackward, name, {a.conv_out, a.out, d_out, a.save_mean, a.save_invstd,
                                                                d_conv_out, grad(bns_[static_cast<size_t>(m.bn)].gamma),
                                                                grad(bns_[static_cast<size_t>(m.bn)].beta)},
                         {a.conv_out, a.out, d_out, a.save_mean, a.save_invstd}, {d_conv_out});
    bn.batchnorm = m.bn;
    bn.writes.push_back(bn.args[6]), bn.writes.push_back(bn.args[7]);
    if (with_dx && dx < 0) dx = g_.tensor(name + ".dx", shape(x));
    const int w = param(m.conv.weight);
    GraphNode& c = node(half_convs() ? OpKind::Conv2dBackwardHalf : OpKind::Conv2dBackward, name,
                        {x, w, d_conv_out, with_dx ? dx : -1, grad(m.conv.weight), grad(m.conv.bias)},
                        {x, w, d_conv_out}, {with_dx ? dx : -1});
    c.pad = m.conv.pad;
    c.writes.push_back(c.args[4]);
    if (c.args[5] >= 0) c.writes.push_back(c.args[5]);
    c.flops = (with_dx ? 2.0 : 1.0) * op::conv2d_flops(shape(d_conv_out), shape(w));
    return dx;
  }

 private:
  Graph& g_;
  ParameterSet& ps_;
  const Backend& backend_;
  const std::vector<BnParams>& bns_;
  bool training_;
  Precision half_, conv_precision_;
};

}  // namespace

PillarSegNet::PillarSegNet(const ModelConfig& config, Backend& backend, uint64_t seed)
    : config_(config), backend_(backend), params_(backend), impl_(std::make_unique<Impl>()) {
  config_.validate();
  // The least any use of the model needs (an evaluation forward of one sample), before the
  // parameters are allocated; each plan is checked again, exactly, before its block is.
  check_model_memory(config_, 1, /*training=*/false, backend_.memory_budget());
  Impl& m = *impl_;
  ParameterSet& ps = params_;
  const auto declare_bn = [&](const std::string& prefix, int channels, float eps, float momentum) {
    BnParams b;
    b.gamma = ps.add_trainable(prefix + ".weight", {channels}, 0, 1.0f);
    b.beta = ps.add_trainable(prefix + ".bias", {channels}, 0, 0.0f);
    b.mean = ps.add_buffer(prefix + ".running_mean", {channels}, 0.0f);
    b.var = ps.add_buffer(prefix + ".running_var", {channels}, 1.0f);
    b.counter = prefix + ".num_batches_tracked";
    ps.add_counter(b.counter);
    b.eps = eps, b.momentum = momentum, b.module_momentum = momentum;
    m.bns.push_back(b);
    return static_cast<int>(m.bns.size()) - 1;
  };
  const auto declare_double_conv = [&](const std::string& prefix, int in, int out, int mid) {
    DoubleConv d;
    d.first.conv = declare_conv(ps, prefix + ".double_conv.0", in, mid, 3, true);
    d.first.bn = declare_bn(prefix + ".double_conv.1", mid, 1e-5f, 0.1f);
    d.second.conv = declare_conv(ps, prefix + ".double_conv.3", mid, out, 3, true);
    d.second.bn = declare_bn(prefix + ".double_conv.4", out, 1e-5f, 0.1f);
    return d;
  };
  const int C = config_.pillar_channels, b = config_.base_width, depth = config_.depth;
  if (config_.pillar_input) {
    m.pfn_weight = ps.add_trainable("vfe.pfn_layers.0.linear.weight", {C, 10}, 10);
    m.pfn_bn = declare_bn("vfe.pfn_layers.0.norm", C, 1e-3f, 0.01f);
  }
  if (config_.occupancy != OccupancyInput::None) {
    m.occupancy.conv =
        declare_conv(ps, "occupancy.conv", config_.occupancy_input_channels(), config_.occupancy_channels, 3, false);
    m.occupancy.bn = declare_bn("occupancy.norm", config_.occupancy_channels, 1e-3f, 0.01f);
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
    d.conv = declare_double_conv(fmt::format("segmentation_head.down{}.maxpool_conv.1", i), d.in, d.out, d.out);
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
    u.conv = declare_double_conv(prefix + ".conv", cat, out, mid);
    current = out;
    m.ups.push_back(std::move(u));
  }
  m.head = declare_conv(ps, "segmentation_head.outc.conv", current, config_.num_classes, 1, true);
  params_.finalize(seed);
}

PillarSegNet::~PillarSegNet() = default;

void PillarSegNet::set_batchnorm_momentum(float momentum) {
  PS_CHECK(momentum <= 1, "BatchNorm momentum must be at most 1, got {}", momentum);
  for (BnParams& bn : impl_->bns) bn.momentum = momentum > 0 ? momentum : bn.module_momentum;
}

void PillarSegNet::set_replicas(ReplicaSum* replicas) {
  std::string why;
  PS_CHECK(replicas == nullptr || backend_.supports_synchronized_batchnorm(&why), "data-parallel training: {}", why);
  impl_->replicas = replicas;
}

// The graph of the evaluation forward (training: the training step) for `batch` samples and the
// current pillar capacity.
void PillarSegNet::build_graph(GraphPlan& p, int batch, bool training) {
  Impl& m = *impl_;
  ParameterSet& ps = params_;
  p.graph = Graph();
  Graph& g = p.graph;
  p.precision = training ? m.train_precision : m.precision;
  Builder bld(g, ps, backend_, m.bns, training, p.precision);
  const int H = config_.grid.height(), W = config_.grid.width(), depth = config_.depth;
  const int64_t N = config_.max_points_per_pillar, C = config_.pillar_channels, cap = m.pillar_capacity;
  const int K = config_.num_classes;
  const bool pillars = config_.pillar_input, occupancy = config_.occupancy != OccupancyInput::None;

  // Inputs: the canvas, the pillar buffers and the input maps (uploaded or prepared on the device).
  // A mixed-precision evaluation of pillars alone scatters them straight into the U-Net's 16-bit
  // input; with other streams the canvas is FP32 and rounded once it is whole.
  const bool half_canvas = bld.half() && pillars && !occupancy && !config_.grid_map_input;
  const int canvas =
      g.tensor(half_canvas ? "canvas16" : "canvas", {batch, config_.input_channels(), H, W},
               half_canvas ? DType::U16 : DType::F32);
  int pfn_out = -1, pfn_argmax = -1, pfn_mean = -1, pfn_invstd = -1;
  if (pillars) {
    p.pillar_points = g.tensor("pillar_points", {cap, N, 10});
    p.pillar_cells = g.tensor("pillar_cells", {cap, 3}, DType::I32);
    pfn_out = g.tensor("pfn.out", {cap, C});
    for (int id : {p.pillar_points, p.pillar_cells, pfn_out}) g.at(id).dynamic_rows = true;
    g.at(p.pillar_points).input = g.at(p.pillar_cells).input = true;
    if (training) {
      pfn_argmax = g.tensor("pfn.argmax", {cap, C}, DType::I32);
      g.at(pfn_argmax).dynamic_rows = true;
      std::tie(pfn_mean, pfn_invstd) = bld.saved_stats("pfn", static_cast<int>(C));
    }
  }
  if (occupancy) {
    p.occupancy_input = g.tensor("occupancy_input", {batch, config_.occupancy_input_channels(), H, W});
    g.at(p.occupancy_input).input = true;
  }
  if (config_.grid_map_input) {
    p.grid_map_input = g.tensor("grid_map_input", {batch, 6, H, W});
    g.at(p.grid_map_input).input = true;
  }

  // ---- the forward ----
  bld.stage = pillars ? Stage::Pfn : occupancy ? Stage::Occupancy : Stage::UNet;
  bld.node(OpKind::FillZero, "canvas", {canvas}, {}, {canvas});
  int channel = 0;
  if (pillars) {
    const int w = bld.param(m.pfn_weight);
    GraphNode& pfn =
        bld.node(OpKind::PfnForward, "pfn", {p.pillar_points, w, pfn_argmax, pfn_out, pfn_mean, pfn_invstd},
                 {p.pillar_points, w}, {pfn_argmax, pfn_out, pfn_mean, pfn_invstd});
    pfn.batchnorm = m.pfn_bn;
    pfn.training = training;
    pfn.flops = op::pfn_flops({cap, N, 10}, {C, 10});
    bld.stage = Stage::Scatter;
    GraphNode& scatter =
        bld.node(half_canvas ? OpKind::ScatterHalf : OpKind::Scatter, "pfn",
                 {pfn_out, p.pillar_cells, canvas}, {pfn_out, p.pillar_cells, canvas}, {canvas});
    scatter.channel0 = 0;
    channel += config_.pillar_channels;
  }
  Builder::Activations occ;
  const int occupancy_channel = channel;
  if (occupancy) {
    bld.stage = Stage::Occupancy;
    occ = bld.conv_bn_relu("occupancy", m.occupancy, p.occupancy_input);
    GraphNode& copy = bld.node(OpKind::CopyChannels, "occupancy", {occ.out, canvas}, {occ.out, canvas}, {canvas});
    copy.channel0 = channel;
    channel += config_.occupancy_channels;
  }
  bld.stage = Stage::UNet;
  if (config_.grid_map_input) {
    GraphNode& copy = bld.node(OpKind::CopyChannels, "grid_map", {p.grid_map_input, canvas},
                               {p.grid_map_input, canvas}, {canvas});
    copy.channel0 = channel;
  }
  // Mixed precision: the U-Net runs on a 16-bit copy of the canvas.
  int unet_input = canvas;
  if (bld.half() && !half_canvas) {
    unet_input = g.tensor("canvas16", g.at(canvas).shape, DType::U16);
    bld.node(OpKind::ToHalf, "canvas", {canvas, unet_input}, {canvas}, {unet_input});
  }
  bld.unet = true;
  // Level sizes; x[i] is level i's tensor (x[0] the canvas).
  std::vector<int64_t> hs(static_cast<size_t>(depth) + 1, H), ws(static_cast<size_t>(depth) + 1, W);
  for (int i = 1; i <= depth; ++i) {
    hs[static_cast<size_t>(i)] = hs[static_cast<size_t>(i - 1)] / 2;
    ws[static_cast<size_t>(i)] = ws[static_cast<size_t>(i - 1)] / 2;
  }
  // An Up's concatenation buffer, made before the Down whose output is its skip when that output
  // is written straight into it (training, batch 1, no padding: the skip is not kept twice).
  std::vector<int> cat(static_cast<size_t>(depth), -1);
  std::vector<bool> skip_in_cat(static_cast<size_t>(depth), false);
  for (int j = 1; j <= depth; ++j) {
    const Up& u = m.ups[static_cast<size_t>(j - 1)];
    const size_t level = static_cast<size_t>(depth - j);
    cat[static_cast<size_t>(j - 1)] = g.tensor(fmt::format("up{}.cat", j),
                                               {batch, u.skip_channels + u.up_channels, hs[level], ws[level]}, bld.act());
    skip_in_cat[static_cast<size_t>(j - 1)] = training && batch == 1 && depth - j >= 1 &&
                                              2 * hs[level + 1] == hs[level] && 2 * ws[level + 1] == ws[level];
  }
  std::vector<int> x(static_cast<size_t>(depth) + 1, -1);
  x[0] = unet_input;
  struct DownActs {
    int pooled = -1, argmax = -1;
    Builder::Activations first, second;
  };
  std::vector<DownActs> down_acts(static_cast<size_t>(depth));
  for (int i = 1; i <= depth; ++i) {
    const Down& d = m.downs[static_cast<size_t>(i - 1)];
    DownActs& a = down_acts[static_cast<size_t>(i - 1)];
    const std::string name = fmt::format("down{}", i);
    const Shape pooled = op::maxpool2x2(g.at(x[static_cast<size_t>(i - 1)]).shape);
    a.pooled = g.tensor(name + ".pooled", pooled, bld.act());
    if (bld.half()) {
      bld.node(OpKind::MaxPool2x2Half, name, {x[static_cast<size_t>(i - 1)], a.pooled},
               {x[static_cast<size_t>(i - 1)]}, {a.pooled});
    } else {
      a.argmax = g.tensor(name + ".argmax", pooled, DType::I32);
      bld.node(OpKind::MaxPool2x2, name, {x[static_cast<size_t>(i - 1)], a.pooled, a.argmax},
               {x[static_cast<size_t>(i - 1)]}, {a.pooled, a.argmax});
    }
    a.first = bld.conv_bn_relu(name + ".conv1", d.conv.first, a.pooled);
    // Up depth - i takes this level's output as its skip.
    int into = -1;
    if (i < depth && skip_in_cat[static_cast<size_t>(depth - i - 1)]) {
      into = g.view(name + ".out", cat[static_cast<size_t>(depth - i - 1)], {batch, d.out, hs[static_cast<size_t>(i)],
                                                                             ws[static_cast<size_t>(i)]});
    }
    a.second = bld.conv_bn_relu(name + ".conv2", d.conv.second, a.first.out, into);
    x[static_cast<size_t>(i)] = a.second.out;
  }
  struct UpActs {
    int upsampled = -1, cat = -1;
    Builder::Activations first, second;
  };
  std::vector<UpActs> up_acts(static_cast<size_t>(depth));
  int current = x[static_cast<size_t>(depth)];
  for (int j = 1; j <= depth; ++j) {
    const Up& u = m.ups[static_cast<size_t>(j - 1)];
    UpActs& a = up_acts[static_cast<size_t>(j - 1)];
    const std::string name = fmt::format("up{}", j);
    const size_t skip_level = static_cast<size_t>(depth - j);
    const int skip = x[skip_level];
    a.cat = cat[static_cast<size_t>(j - 1)];
    const Shape in = g.at(current).shape;  // a copy: adding tensors below moves the list
    const Shape up_shape = u.transposed ? op::conv_transpose2x2(in, {u.in, u.up_channels, 2, 2}) : op::upsample2x(in);
    // Eval with batch 1 and no padding: the upsampled tensor is the band of the concatenation
    // after the skip, so the upsampling writes its part in place.
    const bool upsampled_in_cat = !training && batch == 1 && up_shape[2] == hs[skip_level] &&
                                  up_shape[3] == ws[skip_level];
    a.upsampled = upsampled_in_cat
                      ? g.view(name + ".upsampled", a.cat, up_shape,
                               static_cast<size_t>(u.skip_channels) * static_cast<size_t>(hs[skip_level]) *
                                   static_cast<size_t>(ws[skip_level]) * dtype_bytes(bld.act()))
                      : g.tensor(name + ".upsampled", up_shape, bld.act());
    if (u.transposed && bld.half_convs()) {
      bld.half_conv_transpose(name + ".up", current, bld.param(u.up.weight), bld.param(u.up.bias), a.upsampled);
    } else if (u.transposed) {
      const int w = bld.param(u.up.weight), bias = bld.param(u.up.bias);
      GraphNode& n = bld.node(OpKind::ConvTranspose2x2, name + ".up", {current, w, bias, a.upsampled},
                              {current, w, bias}, {a.upsampled});
      n.flops = op::conv_transpose2x2_flops(in, g.at(w).shape);
    } else {
      bld.node(bld.half() ? OpKind::Upsample2xHalf : OpKind::Upsample2x, name, {current, a.upsampled}, {current},
               {a.upsampled});
    }
    if (upsampled_in_cat) {
      GraphNode& n = bld.node(bld.half() ? OpKind::CopyChannelsHalf : OpKind::CopyChannels, name + ".skip",
                              {skip, a.cat}, {skip, a.cat}, {a.cat});
      n.channel0 = 0;
    } else if (skip_in_cat[static_cast<size_t>(j - 1)]) {
      GraphNode& n = bld.node(OpKind::CopyChannels, name + ".up", {a.upsampled, a.cat}, {a.upsampled, a.cat}, {a.cat});
      n.channel0 = u.skip_channels;
    } else {
      op::pad_concat(g.at(skip).shape, up_shape);
      bld.node(bld.half() ? OpKind::PadConcatHalf : OpKind::PadConcat, name, {skip, a.upsampled, a.cat},
               {skip, a.upsampled}, {a.cat});
    }
    a.first = bld.conv_bn_relu(name + ".conv1", u.conv.first, a.cat);
    a.second = bld.conv_bn_relu(name + ".conv2", u.conv.second, a.first.out);
    current = a.second.out;
  }
  bld.stage = Stage::Head;
  p.logits = bld.conv("head", m.head, current, "logits");
  p.forward_end = g.size();

  // ---- the loss ----
  bld.stage = Stage::Loss;
  p.labels = g.tensor("labels", {batch, H, W}, DType::U8);
  p.coefficients = g.tensor("coefficients", {K + 1});
  p.d_logits = g.tensor("d_logits", g.at(p.logits).shape);
  op::loss(g.at(p.logits).shape, g.at(p.labels).shape, g.at(p.coefficients).shape);
  p.loss_node = g.size();
  bld.node(OpKind::Loss, "loss", {p.logits, p.labels, p.coefficients, p.d_logits},
           {p.logits, p.labels, p.coefficients}, {p.d_logits});
  p.probs = g.tensor("probs", g.at(p.logits).shape);
  p.predicted = g.tensor("predicted", op::argmax(g.at(p.logits).shape), DType::U8);
  for (int id : {p.logits, p.d_logits, p.probs, p.predicted, p.labels, p.coefficients}) g.at(id).output = true;
  g.at(p.labels).input = g.at(p.coefficients).input = true;

  if (training) {
    // ---- the backward, in the reverse order of the forward ----
    bld.stage = Stage::Backward;
    const Up& last = m.ups.back();
    const UpActs& last_acts = up_acts.back();
    const int head_w = bld.param(m.head.weight);
    int d_current = g.tensor("up" + std::to_string(depth) + ".conv2.d_out", g.at(last_acts.second.out).shape);
    {
      GraphNode& n = bld.node(bld.half_convs() ? OpKind::Conv2dBackwardHalf : OpKind::Conv2dBackward, "head",
                              {last_acts.second.out, head_w, p.d_logits, d_current, bld.grad(m.head.weight),
                               bld.grad(m.head.bias)},
                              {last_acts.second.out, head_w, p.d_logits}, {d_current});
      n.pad = 0;
      n.writes.push_back(n.args[4]), n.writes.push_back(n.args[5]);
      n.flops = 2.0 * op::conv2d_flops(g.at(p.d_logits).shape, g.at(head_w).shape);
    }
    static_cast<void>(last);
    // Level gradients: dx[i] is level i's (dx[0] the canvas's).
    std::vector<int> dx(static_cast<size_t>(depth) + 1, -1);
    for (int j = depth; j >= 1; --j) {
      const Up& u = m.ups[static_cast<size_t>(j - 1)];
      const UpActs& a = up_acts[static_cast<size_t>(j - 1)];
      const std::string name = fmt::format("up{}", j);
      const int input = j == 1 ? x[static_cast<size_t>(depth)] : up_acts[static_cast<size_t>(j - 2)].second.out;
      const int first_d_out = bld.conv_bn_relu_backward(name + ".conv2", u.conv.second, a.first.out, a.second,
                                                        d_current, true);
      const int d_cat = bld.conv_bn_relu_backward(name + ".conv1", u.conv.first, a.cat, a.first, first_d_out, true);
      const size_t skip_level = static_cast<size_t>(depth - j);
      dx[skip_level] = g.tensor(skip_level == 0 ? std::string("d_canvas") : fmt::format("down{}.d_out", skip_level),
                                g.at(x[skip_level]).shape);
      const int d_upsampled = g.tensor(name + ".d_upsampled", g.at(a.upsampled).shape);
      bld.node(OpKind::PadConcatBackward, name, {d_cat, dx[skip_level], d_upsampled}, {d_cat},
               {dx[skip_level], d_upsampled});
      const int d_input = j == 1 ? g.tensor(fmt::format("down{}.d_out", depth), g.at(input).shape)
                                 : g.tensor(fmt::format("up{}.conv2.d_out", j - 1), g.at(input).shape);
      if (u.transposed) {
        const int w = bld.param(u.up.weight);
        GraphNode& n = bld.node(bld.half_convs() ? OpKind::ConvTranspose2x2BackwardHalf : OpKind::ConvTranspose2x2Backward,
                                name + ".up",
                                {input, w, d_upsampled, d_input, bld.grad(u.up.weight), bld.grad(u.up.bias)},
                                {input, w, d_upsampled}, {d_input});
        n.writes.push_back(n.args[4]), n.writes.push_back(n.args[5]);
        n.flops = 2.0 * op::conv_transpose2x2_flops(g.at(input).shape, g.at(w).shape);
      } else {
        bld.node(OpKind::Upsample2xBackward, name, {d_upsampled, d_input}, {d_upsampled}, {d_input});
      }
      if (j == 1) dx[static_cast<size_t>(depth)] = d_input;
      d_current = d_input;
    }
    for (int i = depth; i >= 1; --i) {
      // dx[i] (the block's output gradient) is complete: the Up's skip gradient plus block
      // i + 1's part.
      const Down& d = m.downs[static_cast<size_t>(i - 1)];
      const DownActs& a = down_acts[static_cast<size_t>(i - 1)];
      const std::string name = fmt::format("down{}", i);
      const int first_d_out = bld.conv_bn_relu_backward(name + ".conv2", d.conv.second, a.first.out, a.second,
                                                        dx[static_cast<size_t>(i)], true);
      const int d_pooled = bld.conv_bn_relu_backward(name + ".conv1", d.conv.first, a.pooled, a.first, first_d_out, true);
      const int d_x_part = g.tensor(name + ".d_x_part", g.at(x[static_cast<size_t>(i - 1)]).shape);
      bld.node(OpKind::MaxPool2x2Backward, name, {d_pooled, a.argmax, d_x_part}, {d_pooled, a.argmax}, {d_x_part});
      const int target = dx[static_cast<size_t>(i - 1)];
      bld.node(OpKind::AddInplace, name, {target, d_x_part}, {target, d_x_part}, {target});
    }
    const int d_canvas = dx[0];
    if (pillars) {
      const int pfn_dout = g.tensor("pfn.dout", {cap, C});
      g.at(pfn_dout).dynamic_rows = true;
      bld.node(OpKind::ScatterBackward, "pfn", {d_canvas, p.pillar_cells, pfn_dout}, {d_canvas, p.pillar_cells},
               {pfn_dout});
      const int w = bld.param(m.pfn_weight);
      const BnParams& bn = m.bns[static_cast<size_t>(m.pfn_bn)];
      GraphNode& n = bld.node(OpKind::PfnBackward, "pfn",
                              {p.pillar_points, w, pfn_argmax, pfn_dout, bld.grad(m.pfn_weight), bld.grad(bn.gamma),
                               bld.grad(bn.beta), pfn_mean, pfn_invstd},
                              {p.pillar_points, w, pfn_argmax, pfn_dout, pfn_mean, pfn_invstd}, {});
      n.batchnorm = m.pfn_bn;
      n.writes.push_back(n.args[4]), n.writes.push_back(n.args[5]), n.writes.push_back(n.args[6]);
      n.flops = 2.0 * op::pfn_flops({cap, N, 10}, {C, 10});
    }
    if (occupancy) {
      const int d_out = g.tensor("occupancy.d_out", g.at(occ.out).shape);
      GraphNode& n = bld.node(OpKind::ExtractChannels, "occupancy", {d_canvas, d_out}, {d_canvas}, {d_out});
      n.channel0 = occupancy_channel;
      bld.conv_bn_relu_backward("occupancy", m.occupancy, p.occupancy_input, occ, d_out, false);
    }
  }
  p.batch = batch;
  p.pillar_capacity = m.pillar_capacity;
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
  ParameterSet& ps = params_;
  const std::vector<GraphNode>& nodes = p.graph.nodes();
  const bool have_pillars = m.pillar_rows > 0;
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
      case Stage::GridMap:
      case Stage::UNet: stage_times_.unet += elapsed; break;
      case Stage::Head: stage_times_.head += elapsed; break;
      case Stage::Loss:
      case Stage::Backward: break;
    }
  };
  for (size_t i = begin; i < end; ++i) {
    const GraphNode& n = nodes[i];
    if (&p == &m.eval && prepares_weights(n.op) != prepared_weights_only) {
      if (time_stages_ && (i + 1 == end || nodes[i + 1].stage != n.stage)) lap(n.stage);
      continue;
    }
    const double op_start = time_ops_ ? be.clock_ms() : 0.0;
    const Backend::Counters counted_before = time_ops_ ? be.counters() : Backend::Counters{};
    const auto& a = n.args;
    const auto f = [&](size_t k) { return bind<float>(p, a[k]); };
    const auto ints = [&](size_t k) { return bind<int32_t>(p, a[k]); };
    const auto h = [&](size_t k) { return bind<uint16_t>(p, a[k]); };
    const auto activation = [&](size_t k) {
      const HRef r = bind<uint16_t>(p, a[k]);
      return ActRef{r.data, r.shape, p.graph.at(a[k]).dtype == DType::U16};
    };
    switch (n.op) {
      case OpKind::FillZero:  // of any dtype (the 16-bit canvas)
        be.fill_zero(f(0).data, p.graph.tensor_bytes(a[0], m.pillar_rows));
        break;
      case OpKind::PfnForward: {
        if (!have_pillars) break;
        BatchNormRefs r = batchnorm_refs(p, n, a[4], a[5]);
        IRef argmax = ints(2);
        Ref out = f(3);
        be.pfn_forward(f(0), f(1), r, n.training, n.training ? IRef{} : m.live_rows, argmax, out);
        if (n.training) ps.counters()[m.bns[static_cast<size_t>(n.batchnorm)].counter] += 1;
        break;
      }
      case OpKind::Scatter: {
        if (!have_pillars) break;
        Ref canvas = f(2);
        be.scatter_forward(f(0), ints(1), n.channel0, canvas);
        break;
      }
      case OpKind::ScatterHalf: {
        if (!have_pillars) break;
        HRef canvas = h(2);
        be.scatter_forward_half(f(0), ints(1), n.channel0, p.precision, canvas);
        break;
      }
      case OpKind::CopyChannels: {
        Ref y = f(1);
        be.copy_channels(f(0), n.channel0, y);
        break;
      }
      case OpKind::ExtractChannels: {
        Ref x = f(1);
        be.extract_channels(f(0), n.channel0, x);
        break;
      }
      case OpKind::Conv2d: {
        const Ref bias = f(2);
        Ref y = f(3);
        be.conv2d_forward(f(0), f(1), a[2] >= 0 ? &bias : nullptr, n.pad, y);
        break;
      }
      case OpKind::Conv2dBnReluEval: {
        const Ref bias = f(2);
        Ref y = f(3);
        be.conv2d_bn_relu_eval(f(0), f(1), a[2] >= 0 ? &bias : nullptr, batchnorm_refs(p, n, -1, -1), n.pad, y);
        break;
      }
      case OpKind::BatchNormRelu: {
        BatchNormRefs r = batchnorm_refs(p, n, a[2], a[3]);
        Ref y = f(1);
        be.batchnorm_relu_forward(f(0), r, n.training, y);
        if (n.training) ps.counters()[m.bns[static_cast<size_t>(n.batchnorm)].counter] += 1;
        break;
      }
      case OpKind::MaxPool2x2: {
        Ref y = f(1);
        IRef argmax = ints(2);
        be.maxpool2x2_forward(f(0), y, argmax);
        break;
      }
      case OpKind::Upsample2x: {
        Ref y = f(1);
        be.upsample2x_forward(f(0), y);
        break;
      }
      case OpKind::ConvTranspose2x2: {
        const Ref bias = f(2);
        Ref y = f(3);
        be.conv_transpose2d_forward(f(0), f(1), &bias, y);
        break;
      }
      case OpKind::PrepareConvWeights: {
        const Ref bias = f(1);
        HRef w16 = bind<uint16_t>(p, a[2]);
        Ref bias_out = f(3);
        const BatchNormRefs bn = n.batchnorm >= 0 ? batchnorm_refs(p, n, -1, -1) : BatchNormRefs{};
        be.prepare_conv_weights(f(0), a[1] >= 0 ? &bias : nullptr, n.batchnorm >= 0 ? &bn : nullptr, p.precision, w16,
                                bias_out, h(4));
        break;
      }
      case OpKind::PrepareConvTransposeWeights: {
        const Ref bias = f(1);
        HRef w16 = bind<uint16_t>(p, a[2]);
        Ref bias_out = f(3);
        be.prepare_conv_transpose_weights(f(0), a[1] >= 0 ? &bias : nullptr, p.precision, w16, bias_out);
        break;
      }
      case OpKind::Conv2dHalf:
        be.conv2d_half_forward(activation(0), h(1), h(4), f(2), n.weight, n.pad, n.relu, p.precision, activation(3));
        break;
      case OpKind::ConvTranspose2x2Half:
        be.conv_transpose2x2_half_forward(activation(0), h(1), f(2), n.weight, p.precision, activation(3));
        break;
      case OpKind::ToHalf: {
        HRef y = h(1);
        be.to_half(f(0), p.precision, y);
        break;
      }
      case OpKind::MaxPool2x2Half: {
        HRef y = h(1);
        be.maxpool2x2_half(h(0), p.precision, y);
        break;
      }
      case OpKind::Upsample2xHalf: {
        HRef y = h(1);
        be.upsample2x_half(h(0), p.precision, y);
        break;
      }
      case OpKind::PadConcatHalf: {
        HRef y = h(2);
        be.pad_concat_half(h(0), h(1), y);
        break;
      }
      case OpKind::CopyChannelsHalf: {
        HRef y = h(1);
        be.copy_channels_half(h(0), n.channel0, y);
        break;
      }
      case OpKind::PadConcat: {
        Ref y = f(2);
        be.pad_concat_forward(f(0), f(1), y);
        break;
      }
      case OpKind::Loss: {
        Ref d_logits = f(3);
        loss_value = be.loss(m.loss_kind, f(0), bind<uint8_t>(p, a[1]), f(2), d_logits);
        break;
      }
      case OpKind::Conv2dBackward: {
        Ref dx = f(3), dw = f(4), db = f(5);
        be.conv2d_backward(f(0), f(1), f(2), n.pad, a[3] >= 0 ? &dx : nullptr, dw, a[5] >= 0 ? &db : nullptr);
        break;
      }
      case OpKind::BatchNormReluBackward: {
        const BatchNormRefs r = batchnorm_refs(p, n, a[3], a[4]);
        Ref dx = f(5), dgamma = f(6), dbeta = f(7);
        be.batchnorm_relu_backward(f(0), f(1), f(2), r, dx, dgamma, dbeta);
        break;
      }
      case OpKind::PadConcatBackward: {
        Ref dskip = f(1), dup = f(2);
        be.pad_concat_backward(f(0), dskip, dup);
        break;
      }
      case OpKind::ConvTranspose2x2Backward: {
        Ref dx = f(3), dw = f(4), db = f(5);
        be.conv_transpose2d_backward(f(0), f(1), f(2), dx, dw, &db);
        break;
      }
      case OpKind::Conv2dBackwardHalf: {
        Ref dx = f(3), dw = f(4), db = f(5);
        be.conv2d_backward_half(f(0), f(1), f(2), n.pad, p.precision, a[3] >= 0 ? &dx : nullptr, dw,
                                a[5] >= 0 ? &db : nullptr);
        break;
      }
      case OpKind::ConvTranspose2x2BackwardHalf: {
        Ref dx = f(3), dw = f(4), db = f(5);
        be.conv_transpose2x2_backward_half(f(0), f(1), f(2), p.precision, dx, dw, &db);
        break;
      }
      case OpKind::Upsample2xBackward: {
        Ref dx = f(1);
        be.upsample2x_backward(f(0), dx);
        break;
      }
      case OpKind::MaxPool2x2Backward: {
        Ref dx = f(2);
        be.maxpool2x2_backward(f(0), ints(1), dx);
        break;
      }
      case OpKind::AddInplace: {
        Ref target = f(0);
        be.add_inplace(target, f(1));
        break;
      }
      case OpKind::ScatterBackward: {
        if (!have_pillars) break;
        Ref dfeatures = f(2);
        be.scatter_backward(f(0), ints(1), 0, dfeatures);
        break;
      }
      case OpKind::PfnBackward: {
        Ref dweight = f(4), dgamma = f(5), dbeta = f(6);
        if (!have_pillars) {
          for (const Ref& g : {dweight, dgamma, dbeta}) be.fill_zero(g.data, g.bytes());
          break;
        }
        const BatchNormRefs r = batchnorm_refs(p, n, a[7], a[8]);
        be.pfn_backward(f(0), f(1), r, ints(2), f(3), dweight, dgamma, dbeta);
        break;
      }
    }
    if (time_ops_) {
      OpTime& t = op_times_[op_name(n.op)];
      t.ms += be.clock_ms() - op_start;
      t.flops += n.flops;
      t.bytes += static_cast<double>(p.graph.node_bytes(i, m.pillar_rows));
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
    m.pillar_capacity = std::min(std::max<int64_t>(pillars + pillars / 4, 1024), kMaxInt32Index / N);
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
  const bool replay = !training && !time_stages_ && !time_ops_ && be.supports_capture();

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

double PillarSegNet::loss(const Tensor<uint8_t>& labels, LossKind kind, const std::array<float, 13>& coefficients) {
  Impl& m = *impl_;
  PS_CHECK(m.current != nullptr, "loss() before forward()");
  PS_CHECK(labels.shape() == m.labels.shape, "loss: labels must be {}, got {}", shape_str(m.labels.shape),
           shape_str(labels.shape()));
  backend_.upload(m.labels.data, labels.data(), m.labels.bytes());
  backend_.upload(m.coefficients.data, coefficients.data(), m.coefficients.bytes());
  m.loss_kind = kind;
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
