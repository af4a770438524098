// The modules and op graphs of engine/model/model_graph.hpp.
#include "engine/model/model_graph.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <map>
#include <initializer_list>
#include <string>
#include <utility>
#include <vector>

#include "core/error.hpp"
#include "core/ops.hpp"

namespace pillarseg {

namespace {

ConvParams declare_conv(ParameterSet& ps, const std::string& prefix, int in, int out, int k, bool bias) {
  ConvParams c;
  c.in = in, c.out = out, c.k = k, c.pad = k / 2;
  const int64_t fan_in = int64_t{in} * k * k;
  c.weight = ps.add_trainable(prefix + ".weight", {out, in, k, k}, fan_in);
  if (bias) c.bias = ps.add_trainable(prefix + ".bias", {out}, fan_in);
  return c;
}

}  // namespace

Modules declare_modules(const ModelConfig& config, ParameterSet& ps) {
  Modules m;
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
  const int C = config.pillar_channels, b = config.base_width, depth = config.depth;
  if (config.pillar_input) {
    m.pfn_weight = ps.add_trainable("vfe.pfn_layers.0.linear.weight", {C, 10}, 10);
    m.pfn_bn = declare_bn("vfe.pfn_layers.0.norm", C, 1e-3f, 0.01f);
  }
  if (config.occupancy != OccupancyInput::None) {
    m.occupancy.conv =
        declare_conv(ps, "occupancy.conv", config.occupancy_input_channels(), config.occupancy_channels, 3, false);
    m.occupancy.bn = declare_bn("occupancy.norm", config.occupancy_channels, 1e-3f, 0.01f);
  }
  // Channel counts: c[0] = I; bilinear: c[i] = b * 2^i for i < depth, c[depth] = c[depth-1]
  // (milesial's factor 2); transposed: c[i] = b * 2^i for every i.
  std::vector<int> c(static_cast<size_t>(depth) + 1);
  c[0] = config.input_channels();
  for (int i = 1; i <= depth; ++i) c[i] = b << i;
  if (!config.transposed && depth >= 2) c[depth] = c[depth - 1];
  if (!config.transposed && depth == 1) c[1] = b;
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
    u.transposed = config.transposed;
    u.in = current;
    u.skip_channels = c[skip_level];
    const std::string prefix = fmt::format("segmentation_head.up{}", j);
    if (config.transposed) {
      u.up_channels = current / 2;
      u.up.in = current, u.up.out = current / 2, u.up.k = 2, u.up.pad = 0;
      // PyTorch's fan_in of a ConvTranspose weight (in, out, k, k) is out * k * k.
      u.up.weight = ps.add_trainable(prefix + ".up.weight", {current, current / 2, 2, 2}, int64_t{current / 2} * 4);
      u.up.bias = ps.add_trainable(prefix + ".up.bias", {current / 2}, int64_t{current / 2} * 4);
    } else {
      u.up_channels = current;
    }
    const int cat = u.skip_channels + u.up_channels;
    const int out = skip_level == 0 ? b : (config.transposed ? c[skip_level] : c[skip_level] / 2);
    const int mid = config.transposed ? out : cat / 2;
    u.conv = declare_double_conv(prefix + ".conv", cat, out, mid);
    current = out;
    m.ups.push_back(std::move(u));
  }
  m.head = declare_conv(ps, "segmentation_head.outc.conv", current, config.num_classes, 1, true);
  return m;
}

std::string quantization_key(const std::string& weight_name) {
  const std::string suffix = ".weight";
  PS_CHECK(weight_name.size() > suffix.size() && weight_name.ends_with(suffix),
           "quantization_key: {} is not a weight's name", weight_name);
  return weight_name.substr(0, weight_name.size() - suffix.size());
}

int64_t pillar_capacity_for(int64_t pillars, int64_t points_per_pillar) {
  return std::min(std::max<int64_t>(pillars + pillars / 4, 1024), kMaxInt32Index / points_per_pillar);
}

namespace {

// Emits the nodes of one graph in the order the backend runs them.
class Builder {
 public:
  // `precision`: the convolutions'; the evaluation forward also keeps the U-Net's activations in
  // it, training keeps them (and BatchNorm, the loss, gradients) in FP32.
  // INT8 (evaluation only): the U-Net's convolutions on INT8 weights with the calibrated input
  // quantization of `int8_inputs`, its activations in BF16; the head in FP32 arithmetic (FP32
  // prepared weights) on the U-Net's BF16 last output, the occupancy stream's convolutions in FP32
  // on FP32 tensors.
  Builder(Graph& g, const ParameterSet& ps, const Backend* backend, const std::vector<BnParams>& bns, bool training,
          Precision precision, const std::map<std::string, Int8Input>* int8_inputs)
      : g_(g), ps_(ps), backend_(backend), bns_(bns), training_(training),
        half_(training ? Precision::F32 : precision), conv_precision_(precision), int8_inputs_(int8_inputs) {
    PS_CHECK(!(training && precision == Precision::I8), "INT8 is an inference precision (training runs fp32, bf16 or "
                                                        "fp16)");
  }

  Stage stage = Stage::UNet;
  // 16-bit activations (the evaluation forward in bf16 / fp16).
  bool half() const { return half_ != Precision::F32; }
  // Convolutions on prepared 16-bit weights (the tensor-core kernels), in either graph.
  bool half_convs() const { return conv_precision_ != Precision::F32; }
  bool int8() const { return conv_precision_ == Precision::I8; }
  // The dtype of the 16-bit activations (and of 16-bit prepared weights): BF16 also for INT8.
  DType half_dtype() const { return conv_precision_ == Precision::F16 ? DType::F16 : DType::BF16; }
  // Whether the convolution emitted now runs on prepared weights (16-bit; INT8 in the U-Net,
  // FP32 for the head after it), and their dtype.
  bool prepared_conv() const {
    return int8() ? unet && (stage == Stage::UNet || stage == Stage::Head) : half_convs();
  }
  DType weight_dtype() const {
    if (int8()) return stage == Stage::Head ? DType::F32 : DType::I8;
    return half_dtype();
  }
  // The arithmetic of the evaluation convolution of w_shape emitted now: weight_dtype(), or FP32
  // on the same 16-bit activations where the backend's FP32 kernel for the shape is the faster.
  DType prepared_dtype(const Shape& w_shape, int pad, bool transposed) const {
    if (int8() || training_ || !backend_) return weight_dtype();
    return backend_->prepared_conv_dtype(w_shape, pad, transposed, weight_dtype());
  }
  // The arithmetic of the training step's convolution backward.
  DType compute() const { return half_convs() ? half_dtype() : DType::F32; }
  // The type of the U-Net's activations: 16-bit in a mixed-precision evaluation forward once
  // `unet` is set (the occupancy stream writes the FP32 canvas).
  bool unet = false;
  DType act() const { return half() && unet ? half_dtype() : DType::F32; }

  // A node of the current stage.
  template <class Args>
  GraphNode& add(OpKind op, std::string name, const Args& args, GraphNode attributes = {}) {
    attributes.stage = stage;
    return g_.add(op, std::move(name), args, std::move(attributes));
  }
  static GraphNode with_pad(int pad) {
    GraphNode n;
    n.pad = pad;
    return n;
  }
  static GraphNode with_channel0(int channel0) {
    GraphNode n;
    n.channel0 = channel0;
    return n;
  }
  static GraphNode with_batchnorm(int bn, bool training, int pad = 0) {
    GraphNode n;
    n.batchnorm = bn;
    n.training = training;
    n.pad = pad;
    return n;
  }

  // Mixed precision: a node preparing the 16-bit weights (with the eval BatchNorm `bn` folded
  // in, when >= 0) and the tensor-core convolution x -> y.
  void half_conv(const std::string& name, int x, int w, int b, int bn, int pad, bool relu, int y) {
    const Shape w_shape = shape(w);
    const DType dtype = prepared_dtype(w_shape, pad, false);
    const int w16 = g_.tensor(name + ".w16", op::prepared_conv_weights(w_shape, false, dtype), dtype);
    const int b16 = g_.tensor(name + ".bias16", {w_shape[0]});
    const int scale = dtype == DType::I8 ? g_.tensor(name + ".w8_scale", {w_shape[0]}) : -1;
    // The backend's own transformed form of the weights, where it has one (the CPU's Winograd U).
    const int64_t transform = backend_ ? backend_->prepared_conv_transform_elements(w_shape, pad, dtype) : 0;
    const int wt = transform > 0 ? g_.tensor(name + ".w16_transformed", {transform}, dtype) : -1;
    keep_prepared({w16, b16, wt, scale});
    add(OpKind::PrepareConvWeights, name,
        PrepareConvWeightsArgs{.w = w, .bias = b, .prepared = w16, .prepared_bias = b16, .transformed = wt,
                               .prepared_scale = scale},
        with_batchnorm(bn, false));
    GraphNode n = with_pad(pad);
    n.relu = relu;
    n.weight = w_shape;
    if (dtype == DType::I8) n.int8_input = int8_input(w);
    add(OpKind::PreparedConv2d, name,
        PreparedConv2dArgs{.x = x, .prepared = w16, .prepared_bias = b16, .transformed = wt, .y = y,
                           .prepared_scale = scale},
        n);
  }
  // The same for a transposed 2x2 convolution.
  void half_conv_transpose(const std::string& name, int x, int w, int b, int y) {
    const Shape w_shape = shape(w);
    const DType dtype = prepared_dtype(w_shape, 0, true);
    const int w16 = g_.tensor(name + ".w16", op::prepared_conv_weights(w_shape, true, dtype), dtype);
    const int b16 = g_.tensor(name + ".bias16", {4 * w_shape[1]});
    const int scale = dtype == DType::I8 ? g_.tensor(name + ".w8_scale", {4 * w_shape[1]}) : -1;
    keep_prepared({w16, b16, scale});
    add(OpKind::PrepareConvTransposeWeights, name,
        PrepareConvWeightsArgs{.w = w, .bias = b, .prepared = w16, .prepared_bias = b16, .prepared_scale = scale});
    GraphNode n;
    n.weight = w_shape;
    if (dtype == DType::I8) n.int8_input = int8_input(w);
    add(OpKind::PreparedConvTranspose2d, name,
        PreparedConv2dArgs{.x = x, .prepared = w16, .prepared_bias = b16, .y = y, .prepared_scale = scale}, n);
  }
  // The calibrated input quantization of the convolution whose weight is graph tensor w.
  Int8Input int8_input(int w) const {
    const std::string key = quantization_key(ps_.entries().at(static_cast<size_t>(g_.at(w).parameter)).name);
    const auto it = int8_inputs_ ? int8_inputs_->find(key) : std::map<std::string, Int8Input>::const_iterator{};
    PS_CHECK(int8_inputs_ && it != int8_inputs_->end() && it->second.scale > 0,
             "precision int8: no input scale for the convolution {} (the weights are not calibrated: pillarseg "
             "calibrate writes the scales into a checkpoint)",
             key);
    return it->second;
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

  // Conv2d (with its bias when it has one): x -> y, a new tensor named `out`.
  int conv(const std::string& name, const ConvParams& c, int x, const std::string& out) {
    const int w = param(c.weight), b = param(c.bias);
    const Shape b_shape = b >= 0 ? shape(b) : Shape{};
    const int y = g_.tensor(name + "." + out, op::conv2d(shape(x), shape(w), c.pad, b >= 0 ? &b_shape : nullptr));
    if (prepared_conv()) {
      half_conv(name, x, w, b, -1, c.pad, false, y);
      return y;
    }
    add(OpKind::Conv2d, name, Conv2dArgs{.x = x, .w = w, .bias = b, .y = y}, with_pad(c.pad));
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
    add(OpKind::BatchNormRelu, name, BatchNormReluArgs{.x = x, .y = y, .save_mean = mean, .save_invstd = invstd},
        with_batchnorm(bn, training_));
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
      const auto bn = g_.nodes().back().as<BatchNormReluArgs>();
      a.save_mean = bn.save_mean, a.save_invstd = bn.save_invstd;
      return a;
    }
    const int w = param(m.conv.weight), b = param(m.conv.bias);
    const Shape b_shape = b >= 0 ? shape(b) : Shape{};
    const Shape y_shape = op::conv2d(shape(x), shape(w), m.conv.pad, b >= 0 ? &b_shape : nullptr);
    a.out = into >= 0 ? into : g_.tensor(name + ".out", y_shape, act());
    if (prepared_conv()) {
      half_conv(name, x, w, b, m.bn, m.conv.pad, true, a.out);
      return a;
    }
    add(OpKind::Conv2dBnReluEval, name, Conv2dArgs{.x = x, .w = w, .bias = b, .y = a.out},
        with_batchnorm(m.bn, false, m.conv.pad));
    return a;
  }
  // A convolution's backward: dx (when >= 0), dw and dbias (when the layer has one).
  void conv_backward(const std::string& name, const ConvParams& c, int x, int dy, int dx) {
    GraphNode n = with_pad(c.pad);
    n.compute = compute();
    add(OpKind::Conv2dBackward, name,
        Conv2dBackwardArgs{.x = x, .w = param(c.weight), .dy = dy, .dx = dx, .dw = grad(c.weight),
                           .dbias = grad(c.bias)},
        n);
  }
  // The backward of conv_bn_relu: d_out (written by the consumer) -> BN + ReLU backward in
  // place over d_out, then the conv backward into dx (a new tensor) when `with_dx`.
  int conv_bn_relu_backward(const std::string& name, const ConvBnRelu& m, int x, const Activations& a, int d_out,
                            bool with_dx, int dx = -1) {
    const int d_conv_out = g_.view(name + ".d_conv_out", d_out, shape(a.conv_out));
    const BnParams& bn = bns_[static_cast<size_t>(m.bn)];
    add(OpKind::BatchNormReluBackward, name,
        BatchNormReluBackwardArgs{.x = a.conv_out, .y = a.out, .dy = d_out, .save_mean = a.save_mean,
                                  .save_invstd = a.save_invstd, .dx = d_conv_out, .dgamma = grad(bn.gamma),
                                  .dbeta = grad(bn.beta)},
        with_batchnorm(m.bn, false));
    if (with_dx && dx < 0) dx = g_.tensor(name + ".dx", shape(x));
    conv_backward(name, m.conv, x, d_conv_out, with_dx ? dx : -1);
    return dx;
  }

 private:
  Graph& g_;
  const ParameterSet& ps_;
  const Backend* backend_;  // null: no backend-specific transformed weights (the memory estimate)
  const std::vector<BnParams>& bns_;
  bool training_;
  Precision half_, conv_precision_;
  const std::map<std::string, Int8Input>* int8_inputs_;
};

}  // namespace

void build_model_graph(ModelGraph& out, const ModelConfig& config, const Modules& modules, const ParameterSet& ps,
                       const Backend* backend, int batch, bool training, Precision precision,
                       int64_t pillar_capacity, const std::map<std::string, Int8Input>* int8_inputs) {
  const Modules& m = modules;
  ModelGraph& p = out;
  p = ModelGraph();
  Graph& g = p.graph;
  Builder bld(g, ps, backend, m.bns, training, precision, int8_inputs);
  const int H = config.grid.height(), W = config.grid.width(), depth = config.depth;
  const int64_t N = config.max_points_per_pillar, C = config.pillar_channels, cap = pillar_capacity;
  const int K = config.num_classes;
  const bool pillars = config.pillar_input, occupancy = config.occupancy != OccupancyInput::None;

  // Inputs: the canvas, the pillar buffers and the input maps (uploaded or prepared on the device).
  // A mixed-precision evaluation of pillars alone scatters them straight into the U-Net's 16-bit
  // input; with other streams the canvas is FP32 and rounded once it is whole.
  const bool half_canvas = bld.half() && pillars && !occupancy && !config.grid_map_input;
  // The U-Net's levels and each Up's concatenation buffer first: a Down's output that is an Up's
  // skip is written straight into that Up's buffer where no padding comes between them (training
  // with batch 1 from the first level on; the 16-bit and INT8 evaluation forward with batch 1 from
  // the canvas on, the U-Net's input, so that no skip is copied), and the evaluation's upsampling
  // writes the buffer's other band (below). The buffers then live from their skip's producer on:
  // more planned memory for less traffic (docs/benchmarks.md), which the FP32 evaluation, where
  // the copies are a small share of the time, does not take.
  const DType unet_dtype = bld.half() ? bld.half_dtype() : DType::F32;
  std::vector<int64_t> hs(static_cast<size_t>(depth) + 1, H), ws(static_cast<size_t>(depth) + 1, W);
  for (int i = 1; i <= depth; ++i) {
    hs[static_cast<size_t>(i)] = hs[static_cast<size_t>(i - 1)] / 2;
    ws[static_cast<size_t>(i)] = ws[static_cast<size_t>(i - 1)] / 2;
  }
  std::vector<int> cat(static_cast<size_t>(depth), -1);
  std::vector<bool> skip_in_cat(static_cast<size_t>(depth), false);
  for (int j = 1; j <= depth; ++j) {
    const Up& u = m.ups[static_cast<size_t>(j - 1)];
    const size_t level = static_cast<size_t>(depth - j);
    cat[static_cast<size_t>(j - 1)] = g.tensor(fmt::format("up{}.cat", j),
                                               {batch, u.skip_channels + u.up_channels, hs[level], ws[level]}, unet_dtype);
    skip_in_cat[static_cast<size_t>(j - 1)] = batch == 1 && (training ? depth - j >= 1 : bld.half()) &&
                                              2 * hs[level + 1] == hs[level] && 2 * ws[level + 1] == ws[level];
  }
  // The U-Net's input as the first band of the last Up's buffer (its skip), where that is written
  // in place: the canvas itself when it is in the U-Net's dtype, else its 16-bit copy below.
  const bool input_in_cat = depth >= 1 && !training && skip_in_cat[static_cast<size_t>(depth - 1)];
  const Shape canvas_shape{batch, config.input_channels(), H, W};
  const DType canvas_dtype = half_canvas ? bld.half_dtype() : DType::F32;
  const char* canvas_name = half_canvas ? "canvas16" : "canvas";
  const int canvas = input_in_cat && canvas_dtype == unet_dtype
                         ? g.view(canvas_name, cat[static_cast<size_t>(depth - 1)], canvas_shape)
                         : g.tensor(canvas_name, canvas_shape, canvas_dtype);
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
    p.occupancy_input = g.tensor("occupancy_input", {batch, config.occupancy_input_channels(), H, W});
    g.at(p.occupancy_input).input = true;
  }
  if (config.grid_map_input) {
    p.grid_map_input = g.tensor("grid_map_input", {batch, 6, H, W});
    g.at(p.grid_map_input).input = true;
  }

  // ---- the forward ----
  bld.stage = pillars ? Stage::Pfn : occupancy ? Stage::Occupancy : Stage::UNet;
  bld.add(OpKind::FillZero, "canvas", FillZeroArgs{.y = canvas});
  int channel = 0;
  if (pillars) {
    const int w = bld.param(m.pfn_weight);
    bld.add(OpKind::PfnForward, "pfn",
            PfnForwardArgs{.points = p.pillar_points, .w = w, .argmax = pfn_argmax, .out = pfn_out,
                           .save_mean = pfn_mean, .save_invstd = pfn_invstd},
            Builder::with_batchnorm(m.pfn_bn, training));
    bld.stage = Stage::Scatter;
    bld.add(OpKind::Scatter, "pfn", ScatterArgs{.features = pfn_out, .cells = p.pillar_cells, .canvas = canvas},
            Builder::with_channel0(0));
    channel += config.pillar_channels;
  }
  Builder::Activations occ;
  const int occupancy_channel = channel;
  if (occupancy) {
    bld.stage = Stage::Occupancy;
    occ = bld.conv_bn_relu("occupancy", m.occupancy, p.occupancy_input);
    bld.add(OpKind::CopyChannels, "occupancy", CopyChannelsArgs{.x = occ.out, .y = canvas},
            Builder::with_channel0(channel));
    channel += config.occupancy_channels;
  }
  bld.stage = Stage::UNet;
  if (config.grid_map_input) {
    bld.add(OpKind::CopyChannels, "grid_map", CopyChannelsArgs{.x = p.grid_map_input, .y = canvas},
            Builder::with_channel0(channel));
  }
  // Mixed precision: the U-Net runs on a 16-bit copy of the canvas.
  int unet_input = canvas;
  if (bld.half() && !half_canvas) {
    unet_input = input_in_cat ? g.view("canvas16", cat[static_cast<size_t>(depth - 1)], canvas_shape)
                              : g.tensor("canvas16", canvas_shape, bld.half_dtype());
    bld.add(OpKind::Convert, "canvas", UnaryArgs{.x = canvas, .y = unet_input});
  }
  bld.unet = true;
  // x[i] is level i's tensor (x[0] the canvas).
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
    const Shape pooled = op::maxpool2d(g.at(x[static_cast<size_t>(i - 1)]).shape);
    a.pooled = g.tensor(name + ".pooled", pooled, bld.act());
    // 16-bit activations are pooled without an arg-max (the evaluation forward keeps none).
    if (!bld.half()) a.argmax = g.tensor(name + ".argmax", pooled, DType::I32);
    bld.add(OpKind::MaxPool2d, name, MaxPool2dArgs{.x = x[static_cast<size_t>(i - 1)], .y = a.pooled, .argmax = a.argmax});
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
    const Shape up_shape = u.transposed ? op::conv_transpose2d(in, {u.in, u.up_channels, 2, 2}) : op::upsample_bilinear(in);
    // Eval with batch 1 and no padding: the upsampled tensor is the band of the concatenation
    // after the skip, so the upsampling writes its part in place.
    const bool upsampled_in_cat = !training && batch == 1 && up_shape[2] == hs[skip_level] &&
                                  up_shape[3] == ws[skip_level];
    a.upsampled = upsampled_in_cat
                      ? g.view(name + ".upsampled", a.cat, up_shape,
                               static_cast<size_t>(u.skip_channels) * static_cast<size_t>(hs[skip_level]) *
                                   static_cast<size_t>(ws[skip_level]) * dtype_bytes(bld.act()))
                      : g.tensor(name + ".upsampled", up_shape, bld.act());
    if (u.transposed && bld.prepared_conv()) {
      bld.half_conv_transpose(name + ".up", current, bld.param(u.up.weight), bld.param(u.up.bias), a.upsampled);
    } else if (u.transposed) {
      const int w = bld.param(u.up.weight), bias = bld.param(u.up.bias);
      bld.add(OpKind::ConvTranspose2d, name + ".up", Conv2dArgs{.x = current, .w = w, .bias = bias, .y = a.upsampled});
    } else {
      bld.add(OpKind::UpsampleBilinear, name, UnaryArgs{.x = current, .y = a.upsampled});
    }
    const bool skip_written = skip_in_cat[static_cast<size_t>(j - 1)];
    if (upsampled_in_cat && skip_written) {
      // Both bands were written in place by their producers.
    } else if (upsampled_in_cat) {
      bld.add(OpKind::CopyChannels, name + ".skip", CopyChannelsArgs{.x = skip, .y = a.cat}, Builder::with_channel0(0));
    } else if (skip_written) {
      bld.add(OpKind::CopyChannels, name + ".up", CopyChannelsArgs{.x = a.upsampled, .y = a.cat},
              Builder::with_channel0(u.skip_channels));
    } else {
      bld.add(OpKind::PadConcat, name, PadConcatArgs{.skip = skip, .up = a.upsampled, .y = a.cat});
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
  p.loss_node = g.size();
  bld.add(OpKind::Loss, "loss",
          LossArgs{.logits = p.logits, .labels = p.labels, .coefficients = p.coefficients, .dlogits = p.d_logits});
  p.probs = g.tensor("probs", g.at(p.logits).shape);
  p.predicted = g.tensor("predicted", op::argmax(g.at(p.logits).shape), DType::U8);
  for (int id : {p.logits, p.d_logits, p.probs, p.predicted, p.labels, p.coefficients}) g.at(id).output = true;
  g.at(p.labels).input = g.at(p.coefficients).input = true;

  if (training) {
    // ---- the backward, in the reverse order of the forward ----
    bld.stage = Stage::Backward;
    const UpActs& last_acts = up_acts.back();
    int d_current = g.tensor("up" + std::to_string(depth) + ".conv2.d_out", g.at(last_acts.second.out).shape);
    bld.conv_backward("head", m.head, last_acts.second.out, p.d_logits, d_current);
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
      bld.add(OpKind::PadConcatBackward, name,
              PadConcatBackwardArgs{.dy = d_cat, .dskip = dx[skip_level], .dup = d_upsampled});
      const int d_input = j == 1 ? g.tensor(fmt::format("down{}.d_out", depth), g.at(input).shape)
                                 : g.tensor(fmt::format("up{}.conv2.d_out", j - 1), g.at(input).shape);
      if (u.transposed) {
        GraphNode n;
        n.compute = bld.compute();
        bld.add(OpKind::ConvTranspose2dBackward, name + ".up",
                Conv2dBackwardArgs{.x = input, .w = bld.param(u.up.weight), .dy = d_upsampled, .dx = d_input,
                                   .dw = bld.grad(u.up.weight), .dbias = bld.grad(u.up.bias)},
                n);
      } else {
        bld.add(OpKind::UpsampleBilinearBackward, name, UnaryArgs{.x = d_upsampled, .y = d_input});
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
      bld.add(OpKind::MaxPool2dBackward, name, MaxPool2dBackwardArgs{.dy = d_pooled, .argmax = a.argmax, .dx = d_x_part});
      bld.add(OpKind::AddInplace, name, AddInplaceArgs{.a = dx[static_cast<size_t>(i - 1)], .b = d_x_part});
    }
    const int d_canvas = dx[0];
    if (pillars) {
      const int pfn_dout = g.tensor("pfn.dout", {cap, C});
      g.at(pfn_dout).dynamic_rows = true;
      bld.add(OpKind::ScatterBackward, "pfn",
              ScatterBackwardArgs{.dcanvas = d_canvas, .cells = p.pillar_cells, .dfeatures = pfn_dout});
      const BnParams& bn = m.bns[static_cast<size_t>(m.pfn_bn)];
      bld.add(OpKind::PfnBackward, "pfn",
              PfnBackwardArgs{.points = p.pillar_points, .w = bld.param(m.pfn_weight), .argmax = pfn_argmax,
                              .dout = pfn_dout, .dw = bld.grad(m.pfn_weight), .dgamma = bld.grad(bn.gamma),
                              .dbeta = bld.grad(bn.beta), .save_mean = pfn_mean, .save_invstd = pfn_invstd},
              Builder::with_batchnorm(m.pfn_bn, false));
    }
    if (occupancy) {
      const int d_out = g.tensor("occupancy.d_out", g.at(occ.out).shape);
      bld.add(OpKind::ExtractChannels, "occupancy", ExtractChannelsArgs{.y = d_canvas, .x = d_out},
              Builder::with_channel0(occupancy_channel));
      bld.conv_bn_relu_backward("occupancy", m.occupancy, p.occupancy_input, occ, d_out, false);
    }
  }
}

}  // namespace pillarseg
