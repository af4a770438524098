// The op records of engine/model/op_record.hpp: one entry per op kind, with its shape rule, FLOPs,
// least bytes and the Backend call that runs it (the executor of the model's graphs).
#include <fmt/format.h>

#include <array>
#include <string>

#include "core/error.hpp"
#include "core/ops.hpp"
#include "engine/model/graph.hpp"
#include "engine/model/op_record.hpp"

namespace pillarseg {

TensorRef OpContext::tensor(int id) {
  return id < 0 ? TensorRef{} : TensorRef{data(id), shape(id), graph().at(id).dtype};
}

size_t OpContext::bytes(int id) { return graph().tensor_bytes(id, pillar_rows()); }

namespace {

const Shape& shape_of(const Graph& g, int id) { return g.at(id).shape; }
DType dtype_of(const Graph& g, int id) { return g.at(id).dtype; }

void require_shape(const Graph& g, const GraphNode& n, int id, const Shape& expected, const char* what) {
  if (id < 0) return;
  PS_CHECK(shape_of(g, id) == expected, "graph: node {} ({}): {} must be {}, got {}", n.name, op_name(n.op), what,
           shape_str(expected), shape_str(shape_of(g, id)));
}
void require_same_dtype(const Graph& g, const GraphNode& n, int a, int b) {
  PS_CHECK(dtype_of(g, a) == dtype_of(g, b), "graph: node {} ({}): {} is {} but {} is {}", n.name, op_name(n.op),
           g.at(a).name, dtype_name(dtype_of(g, a)), g.at(b).name, dtype_name(dtype_of(g, b)));
}

// ---- shape rules ----

void check_pfn_forward(const Graph& g, const GraphNode& n) {
  const auto a = n.as<PfnForwardArgs>();
  const Shape out = op::pfn(shape_of(g, a.points), shape_of(g, a.w));
  require_shape(g, n, a.out, out, "out");
  require_shape(g, n, a.argmax, out, "argmax");
}
void check_pfn_backward(const Graph& g, const GraphNode& n) {
  const auto a = n.as<PfnBackwardArgs>();
  require_shape(g, n, a.dout, op::pfn(shape_of(g, a.points), shape_of(g, a.w)), "dout");
  require_shape(g, n, a.dw, shape_of(g, a.w), "dw");
}
void check_scatter(const Graph& g, const GraphNode& n) {
  const auto a = n.as<ScatterArgs>();
  op::scatter(shape_of(g, a.features), shape_of(g, a.cells), shape_of(g, a.canvas), n.channel0);
}
void check_scatter_backward(const Graph& g, const GraphNode& n) {
  const auto a = n.as<ScatterBackwardArgs>();
  op::scatter(shape_of(g, a.dfeatures), shape_of(g, a.cells), shape_of(g, a.dcanvas), n.channel0);
}
void check_copy_channels(const Graph& g, const GraphNode& n) {
  const auto a = n.as<CopyChannelsArgs>();
  op::channel_band(shape_of(g, a.x), shape_of(g, a.y), n.channel0);
  require_same_dtype(g, n, a.x, a.y);
}
void check_extract_channels(const Graph& g, const GraphNode& n) {
  const auto a = n.as<ExtractChannelsArgs>();
  op::channel_band(shape_of(g, a.x), shape_of(g, a.y), n.channel0);
}
void check_conv2d(const Graph& g, const GraphNode& n) {
  const auto a = n.as<Conv2dArgs>();
  const Shape* bias = a.bias >= 0 ? &shape_of(g, a.bias) : nullptr;
  require_shape(g, n, a.y, op::conv2d(shape_of(g, a.x), shape_of(g, a.w), n.pad, bias), "y");
}
void check_conv2d_backward(const Graph& g, const GraphNode& n) {
  const auto a = n.as<Conv2dBackwardArgs>();
  require_shape(g, n, a.dy, op::conv2d(shape_of(g, a.x), shape_of(g, a.w), n.pad), "dy");
  require_shape(g, n, a.dx, shape_of(g, a.x), "dx");
  require_shape(g, n, a.dw, shape_of(g, a.w), "dw");
  require_shape(g, n, a.dbias, {shape_of(g, a.w)[0]}, "dbias");
}
void check_conv_transpose2d(const Graph& g, const GraphNode& n) {
  const auto a = n.as<Conv2dArgs>();
  const Shape* bias = a.bias >= 0 ? &shape_of(g, a.bias) : nullptr;
  require_shape(g, n, a.y, op::conv_transpose2d(shape_of(g, a.x), shape_of(g, a.w), bias), "y");
}
void check_conv_transpose2d_backward(const Graph& g, const GraphNode& n) {
  const auto a = n.as<Conv2dBackwardArgs>();
  require_shape(g, n, a.dy, op::conv_transpose2d(shape_of(g, a.x), shape_of(g, a.w)), "dy");
  require_shape(g, n, a.dx, shape_of(g, a.x), "dx");
  require_shape(g, n, a.dw, shape_of(g, a.w), "dw");
  require_shape(g, n, a.dbias, {shape_of(g, a.w)[1]}, "dbias");
}
void check_batchnorm_relu(const Graph& g, const GraphNode& n) {
  const auto a = n.as<BatchNormReluArgs>();
  const Shape& x = shape_of(g, a.x);
  require_shape(g, n, a.y, op::batchnorm(x, {x.at(1)}), "y");
  require_shape(g, n, a.save_mean, {x.at(1)}, "save_mean");
}
void check_batchnorm_relu_backward(const Graph& g, const GraphNode& n) {
  const auto a = n.as<BatchNormReluBackwardArgs>();
  const Shape& x = shape_of(g, a.x);
  for (int id : {a.y, a.dy, a.dx}) require_shape(g, n, id, x, g.at(id).name.c_str());
  require_shape(g, n, a.dgamma, {x.at(1)}, "dgamma");
}
void check_maxpool2d(const Graph& g, const GraphNode& n) {
  const auto a = n.as<MaxPool2dArgs>();
  const Shape y = op::maxpool2d(shape_of(g, a.x));
  require_shape(g, n, a.y, y, "y");
  require_shape(g, n, a.argmax, y, "argmax");
  require_same_dtype(g, n, a.x, a.y);
  PS_CHECK(a.argmax >= 0 || is_float16(dtype_of(g, a.x)), "graph: node {} (maxpool2d): FP32 needs its arg-max",
           n.name);
}
void check_maxpool2d_backward(const Graph& g, const GraphNode& n) {
  const auto a = n.as<MaxPool2dBackwardArgs>();
  require_shape(g, n, a.dy, op::maxpool2d(shape_of(g, a.dx)), "dy");
  require_shape(g, n, a.argmax, shape_of(g, a.dy), "argmax");
}
void check_upsample(const Graph& g, const GraphNode& n) {
  const auto a = n.as<UnaryArgs>();
  require_shape(g, n, a.y, op::upsample_bilinear(shape_of(g, a.x)), "y");
  require_same_dtype(g, n, a.x, a.y);
}
void check_upsample_backward(const Graph& g, const GraphNode& n) {
  const auto a = n.as<UnaryArgs>();  // x: dy, y: dx
  require_shape(g, n, a.x, op::upsample_bilinear(shape_of(g, a.y)), "dy");
}
void check_pad_concat(const Graph& g, const GraphNode& n) {
  const auto a = n.as<PadConcatArgs>();
  require_shape(g, n, a.y, op::pad_concat(shape_of(g, a.skip), shape_of(g, a.up)), "y");
  require_same_dtype(g, n, a.skip, a.y);
  require_same_dtype(g, n, a.up, a.y);
}
void check_pad_concat_backward(const Graph& g, const GraphNode& n) {
  const auto a = n.as<PadConcatBackwardArgs>();
  require_shape(g, n, a.dy, op::pad_concat(shape_of(g, a.dskip), shape_of(g, a.dup)), "dy");
}
void check_add_inplace(const Graph& g, const GraphNode& n) {
  const auto a = n.as<AddInplaceArgs>();
  op::add_inplace(shape_of(g, a.a), shape_of(g, a.b));
}
void check_loss(const Graph& g, const GraphNode& n) {
  const auto a = n.as<LossArgs>();
  require_shape(g, n, a.dlogits,
                op::loss(shape_of(g, a.logits), shape_of(g, a.labels), shape_of(g, a.coefficients)), "dlogits");
}
// INT8 weights come with their per-output-channel scales (rows of the prepared weights), 16-bit
// ones without.
void check_prepared_scale(const Graph& g, const GraphNode& n, int prepared, int scale) {
  const bool int8 = dtype_of(g, prepared) == DType::I8;
  PS_CHECK(int8 == (scale >= 0), "graph: node {} ({}): {} weights {} a prepared_scale", n.name, op_name(n.op),
           dtype_name(dtype_of(g, prepared)), int8 ? "need" : "take no");
  require_shape(g, n, scale, {shape_of(g, prepared).at(0)}, "prepared_scale");
}

void check_prepare_conv(const Graph& g, const GraphNode& n) {
  const auto a = n.as<PrepareConvWeightsArgs>();
  check_prepared_scale(g, n, a.prepared, a.prepared_scale);
  const Shape& w = shape_of(g, a.w);
  require_shape(g, n, a.prepared, op::prepared_conv_weights(w, false, dtype_of(g, a.prepared)), "prepared");
  require_shape(g, n, a.prepared_bias, {w.at(0)}, "prepared_bias");
  require_shape(g, n, a.bias, {w.at(0)}, "bias");
}
void check_prepare_conv_transpose(const Graph& g, const GraphNode& n) {
  const auto a = n.as<PrepareConvWeightsArgs>();
  check_prepared_scale(g, n, a.prepared, a.prepared_scale);
  const Shape& w = shape_of(g, a.w);
  require_shape(g, n, a.prepared, op::prepared_conv_weights(w, true, dtype_of(g, a.prepared)), "prepared");
  require_shape(g, n, a.prepared_bias, {4 * w.at(1)}, "prepared_bias");
  require_shape(g, n, a.bias, {w.at(1)}, "bias");
}
void check_prepared_conv2d(const Graph& g, const GraphNode& n) {
  const auto a = n.as<PreparedConv2dArgs>();
  check_prepared_scale(g, n, a.prepared, a.prepared_scale);
  PS_CHECK(dtype_of(g, a.prepared) != DType::I8 || n.int8_input.scale > 0, "graph: node {} ({}): INT8 needs an input scale",
           n.name, op_name(n.op));
  require_shape(g, n, a.y, op::conv2d(shape_of(g, a.x), n.weight, n.pad), "y");
  require_shape(g, n, a.prepared, op::prepared_conv_weights(n.weight, false, dtype_of(g, a.prepared)), "prepared");
}
void check_prepared_conv_transpose2d(const Graph& g, const GraphNode& n) {
  const auto a = n.as<PreparedConv2dArgs>();
  check_prepared_scale(g, n, a.prepared, a.prepared_scale);
  PS_CHECK(dtype_of(g, a.prepared) != DType::I8 || n.int8_input.scale > 0, "graph: node {} ({}): INT8 needs an input scale",
           n.name, op_name(n.op));
  require_shape(g, n, a.y, op::conv_transpose2d(shape_of(g, a.x), n.weight), "y");
  require_shape(g, n, a.prepared, op::prepared_conv_weights(n.weight, true, dtype_of(g, a.prepared)), "prepared");
}
void check_convert(const Graph& g, const GraphNode& n) {
  const auto a = n.as<UnaryArgs>();
  require_shape(g, n, a.y, shape_of(g, a.x), "y");
}

// ---- FLOPs ----

double conv2d_flops(const Graph& g, const GraphNode& n) {
  const auto a = n.as<Conv2dArgs>();
  return op::conv2d_flops(shape_of(g, a.y), shape_of(g, a.w));
}
double conv2d_backward_flops(const Graph& g, const GraphNode& n) {  // dx and dw, or dw alone
  const auto a = n.as<Conv2dBackwardArgs>();
  return (a.dx >= 0 ? 2.0 : 1.0) * op::conv2d_flops(shape_of(g, a.dy), shape_of(g, a.w));
}
double conv_transpose2d_flops(const Graph& g, const GraphNode& n) {
  const auto a = n.as<Conv2dArgs>();
  return op::conv_transpose2d_flops(shape_of(g, a.x), shape_of(g, a.w));
}
double conv_transpose2d_backward_flops(const Graph& g, const GraphNode& n) {
  const auto a = n.as<Conv2dBackwardArgs>();
  return 2.0 * op::conv_transpose2d_flops(shape_of(g, a.x), shape_of(g, a.w));
}
double pfn_flops(const Graph& g, const GraphNode& n) {
  const auto a = n.as<PfnForwardArgs>();
  return op::pfn_flops(shape_of(g, a.points), shape_of(g, a.w));
}
double pfn_backward_flops(const Graph& g, const GraphNode& n) {
  const auto a = n.as<PfnBackwardArgs>();
  return 2.0 * op::pfn_flops(shape_of(g, a.points), shape_of(g, a.w));
}
double prepared_conv2d_flops(const Graph& g, const GraphNode& n) {
  return op::conv2d_flops(shape_of(g, n.as<PreparedConv2dArgs>().y), n.weight);
}
double prepared_conv_transpose2d_flops(const Graph& g, const GraphNode& n) {
  return op::conv_transpose2d_flops(shape_of(g, n.as<PreparedConv2dArgs>().x), n.weight);
}

// ---- least bytes of the ops that name a whole tensor of which they move a band or some rows
// (for its lifetime): the band's or the rows' bytes ----

size_t elements(const Graph& g, int id, int64_t rows) {
  return g.tensor_bytes(id, rows) / dtype_bytes(dtype_of(g, id));
}
size_t copy_channels_bytes(const Graph& g, const GraphNode& n, int64_t rows) {  // x -> the band of y
  const auto a = n.as<CopyChannelsArgs>();
  return g.tensor_bytes(a.x, rows) + elements(g, a.x, rows) * dtype_bytes(dtype_of(g, a.y));
}
size_t extract_channels_bytes(const Graph& g, const GraphNode& n, int64_t rows) {  // the band of y -> x
  return 2 * g.tensor_bytes(n.as<ExtractChannelsArgs>().x, rows);
}
size_t scatter_bytes(const Graph& g, const GraphNode& n, int64_t rows) {  // one canvas value per feature
  const auto a = n.as<ScatterArgs>();
  return g.tensor_bytes(a.features, rows) + g.tensor_bytes(a.cells, rows) +
         elements(g, a.features, rows) * dtype_bytes(dtype_of(g, a.canvas));
}
size_t scatter_backward_bytes(const Graph& g, const GraphNode& n, int64_t rows) {
  const auto a = n.as<ScatterBackwardArgs>();
  return 2 * g.tensor_bytes(a.dfeatures, rows) + g.tensor_bytes(a.cells, rows);
}

// ---- the Backend calls ----

double run_fill_zero(OpContext& c, const GraphNode& n) {  // of any dtype (the 16-bit canvas)
  const int y = n.as<FillZeroArgs>().y;
  c.backend().fill_zero(c.data(y), c.bytes(y));
  return 0;
}
double run_pfn_forward(OpContext& c, const GraphNode& n) {
  if (c.pillar_rows() == 0) return 0;
  const auto a = n.as<PfnForwardArgs>();
  BatchNormRefs bn = c.batchnorm(n, a.save_mean, a.save_invstd);
  IRef argmax = c.i32(a.argmax);
  Ref out = c.f32(a.out);
  c.backend().pfn_forward(c.f32(a.points), c.f32(a.w), bn, n.training, n.training ? IRef{} : c.live_rows(), argmax,
                          out);
  if (n.training) c.batchnorm_ran(n);
  return 0;
}
double run_pfn_backward(OpContext& c, const GraphNode& n) {
  const auto a = n.as<PfnBackwardArgs>();
  Ref dweight = c.f32(a.dw), dgamma = c.f32(a.dgamma), dbeta = c.f32(a.dbeta);
  if (c.pillar_rows() == 0) {
    for (const Ref& g : {dweight, dgamma, dbeta}) c.backend().fill_zero(g.data, g.bytes());
    return 0;
  }
  const BatchNormRefs bn = c.batchnorm(n, a.save_mean, a.save_invstd);
  c.backend().pfn_backward(c.f32(a.points), c.f32(a.w), bn, c.i32(a.argmax), c.f32(a.dout), dweight, dgamma, dbeta);
  return 0;
}
double run_scatter(OpContext& c, const GraphNode& n) {
  if (c.pillar_rows() == 0) return 0;
  const auto a = n.as<ScatterArgs>();
  c.backend().scatter_forward(c.f32(a.features), c.i32(a.cells), n.channel0, c.tensor(a.canvas));
  return 0;
}
double run_scatter_backward(OpContext& c, const GraphNode& n) {
  if (c.pillar_rows() == 0) return 0;
  const auto a = n.as<ScatterBackwardArgs>();
  Ref dfeatures = c.f32(a.dfeatures);
  c.backend().scatter_backward(c.f32(a.dcanvas), c.i32(a.cells), n.channel0, dfeatures);
  return 0;
}
double run_copy_channels(OpContext& c, const GraphNode& n) {
  const auto a = n.as<CopyChannelsArgs>();
  c.backend().copy_channels(c.tensor(a.x), n.channel0, c.tensor(a.y));
  return 0;
}
double run_extract_channels(OpContext& c, const GraphNode& n) {
  const auto a = n.as<ExtractChannelsArgs>();
  Ref x = c.f32(a.x);
  c.backend().extract_channels(c.f32(a.y), n.channel0, x);
  return 0;
}
double run_conv2d(OpContext& c, const GraphNode& n) {
  const auto a = n.as<Conv2dArgs>();
  const Ref bias = c.f32(a.bias);
  Ref y = c.f32(a.y);
  c.backend().conv2d_forward(c.f32(a.x), c.f32(a.w), a.bias >= 0 ? &bias : nullptr, n.pad, y);
  return 0;
}
double run_conv2d_bn_relu_eval(OpContext& c, const GraphNode& n) {
  const auto a = n.as<Conv2dArgs>();
  const Ref bias = c.f32(a.bias);
  Ref y = c.f32(a.y);
  c.backend().conv2d_bn_relu_eval(c.f32(a.x), c.f32(a.w), a.bias >= 0 ? &bias : nullptr, c.batchnorm(n, -1, -1),
                                  n.pad, y);
  return 0;
}
double run_conv2d_backward(OpContext& c, const GraphNode& n) {
  const auto a = n.as<Conv2dBackwardArgs>();
  Ref dx = c.f32(a.dx), dw = c.f32(a.dw), db = c.f32(a.dbias);
  c.backend().conv2d_backward(c.f32(a.x), c.f32(a.w), c.f32(a.dy), n.pad, a.dx >= 0 ? &dx : nullptr, dw,
                              a.dbias >= 0 ? &db : nullptr, n.compute);
  return 0;
}
double run_conv_transpose2d(OpContext& c, const GraphNode& n) {
  const auto a = n.as<Conv2dArgs>();
  const Ref bias = c.f32(a.bias);
  Ref y = c.f32(a.y);
  c.backend().conv_transpose2d_forward(c.f32(a.x), c.f32(a.w), &bias, y);
  return 0;
}
double run_conv_transpose2d_backward(OpContext& c, const GraphNode& n) {
  const auto a = n.as<Conv2dBackwardArgs>();
  Ref dx = c.f32(a.dx), dw = c.f32(a.dw), db = c.f32(a.dbias);
  c.backend().conv_transpose2d_backward(c.f32(a.x), c.f32(a.w), c.f32(a.dy), dx, dw, &db, n.compute);
  return 0;
}
double run_batchnorm_relu(OpContext& c, const GraphNode& n) {
  const auto a = n.as<BatchNormReluArgs>();
  BatchNormRefs bn = c.batchnorm(n, a.save_mean, a.save_invstd);
  Ref y = c.f32(a.y);
  c.backend().batchnorm_relu_forward(c.f32(a.x), bn, n.training, y);
  if (n.training) c.batchnorm_ran(n);
  return 0;
}
double run_batchnorm_relu_backward(OpContext& c, const GraphNode& n) {
  const auto a = n.as<BatchNormReluBackwardArgs>();
  const BatchNormRefs bn = c.batchnorm(n, a.save_mean, a.save_invstd);
  Ref dx = c.f32(a.dx), dgamma = c.f32(a.dgamma), dbeta = c.f32(a.dbeta);
  c.backend().batchnorm_relu_backward(c.f32(a.x), c.f32(a.y), c.f32(a.dy), bn, dx, dgamma, dbeta);
  return 0;
}
double run_maxpool2d(OpContext& c, const GraphNode& n) {
  const auto a = n.as<MaxPool2dArgs>();
  IRef argmax = c.i32(a.argmax);
  c.backend().maxpool2d_forward(c.tensor(a.x), c.tensor(a.y), a.argmax >= 0 ? &argmax : nullptr);
  return 0;
}
double run_maxpool2d_backward(OpContext& c, const GraphNode& n) {
  const auto a = n.as<MaxPool2dBackwardArgs>();
  Ref dx = c.f32(a.dx);
  c.backend().maxpool2d_backward(c.f32(a.dy), c.i32(a.argmax), dx);
  return 0;
}
double run_upsample(OpContext& c, const GraphNode& n) {
  const auto a = n.as<UnaryArgs>();
  c.backend().upsample_bilinear_forward(c.tensor(a.x), c.tensor(a.y));
  return 0;
}
double run_upsample_backward(OpContext& c, const GraphNode& n) {
  const auto a = n.as<UnaryArgs>();
  Ref dx = c.f32(a.y);
  c.backend().upsample_bilinear_backward(c.f32(a.x), dx);
  return 0;
}
double run_pad_concat(OpContext& c, const GraphNode& n) {
  const auto a = n.as<PadConcatArgs>();
  c.backend().pad_concat_forward(c.tensor(a.skip), c.tensor(a.up), c.tensor(a.y));
  return 0;
}
double run_pad_concat_backward(OpContext& c, const GraphNode& n) {
  const auto a = n.as<PadConcatBackwardArgs>();
  Ref dskip = c.f32(a.dskip), dup = c.f32(a.dup);
  c.backend().pad_concat_backward(c.f32(a.dy), dskip, dup);
  return 0;
}
double run_add_inplace(OpContext& c, const GraphNode& n) {
  const auto a = n.as<AddInplaceArgs>();
  Ref target = c.f32(a.a);
  c.backend().add_inplace(target, c.f32(a.b));
  return 0;
}
double run_loss(OpContext& c, const GraphNode& n) {
  const auto a = n.as<LossArgs>();
  Ref dlogits = c.f32(a.dlogits);
  return c.backend().loss(c.loss_spec(), c.f32(a.logits), c.ref<uint8_t>(a.labels), c.f32(a.coefficients),
                          dlogits);
}
double run_prepare_conv(OpContext& c, const GraphNode& n) {
  const auto a = n.as<PrepareConvWeightsArgs>();
  const Ref bias = c.f32(a.bias);
  Ref prepared_bias = c.f32(a.prepared_bias);
  const BatchNormRefs bn = n.batchnorm >= 0 ? c.batchnorm(n, -1, -1) : BatchNormRefs{};
  const Ref scale = c.f32(a.prepared_scale);
  c.backend().prepare_conv_weights(c.f32(a.w), a.bias >= 0 ? &bias : nullptr, n.batchnorm >= 0 ? &bn : nullptr,
                                   c.tensor(a.prepared), prepared_bias, c.tensor(a.transformed),
                                   a.prepared_scale >= 0 ? &scale : nullptr);
  return 0;
}
double run_prepare_conv_transpose(OpContext& c, const GraphNode& n) {
  const auto a = n.as<PrepareConvWeightsArgs>();
  const Ref bias = c.f32(a.bias);
  Ref prepared_bias = c.f32(a.prepared_bias);
  const Ref scale = c.f32(a.prepared_scale);
  c.backend().prepare_conv_transpose_weights(c.f32(a.w), a.bias >= 0 ? &bias : nullptr, c.tensor(a.prepared),
                                             prepared_bias, a.prepared_scale >= 0 ? &scale : nullptr);
  return 0;
}
double run_prepared_conv2d(OpContext& c, const GraphNode& n) {
  const auto a = n.as<PreparedConv2dArgs>();
  const Ref scale = c.f32(a.prepared_scale);
  c.backend().conv2d_prepared_forward(c.tensor(a.x), c.tensor(a.prepared), c.tensor(a.transformed),
                                      c.f32(a.prepared_bias), n.weight, n.pad, n.relu, c.tensor(a.y),
                                      a.prepared_scale >= 0 ? &scale : nullptr, n.int8_input);
  return 0;
}
double run_prepared_conv_transpose2d(OpContext& c, const GraphNode& n) {
  const auto a = n.as<PreparedConv2dArgs>();
  const Ref scale = c.f32(a.prepared_scale);
  c.backend().conv_transpose2d_prepared_forward(c.tensor(a.x), c.tensor(a.prepared), c.f32(a.prepared_bias), n.weight,
                                                c.tensor(a.y), a.prepared_scale >= 0 ? &scale : nullptr,
                                                n.int8_input);
  return 0;
}
double run_convert(OpContext& c, const GraphNode& n) {
  const auto a = n.as<UnaryArgs>();
  c.backend().convert(c.f32(a.x), c.tensor(a.y));
  return 0;
}

constexpr Access R = Access::Read, W = Access::Write, RW = Access::ReadWrite;
constexpr bool kOptional = true;

std::vector<OpRecord> make_records() {
  std::vector<OpRecord> r = {
      {OpKind::FillZero, "fill zero", {{"y", W, kActivation}}, nullptr, nullptr, nullptr, run_fill_zero},
      {OpKind::PfnForward, "pfn forward",
       {{"points", R, kF32}, {"w", R, kF32}, {"argmax", W, kI32, kOptional}, {"out", W, kF32},
        {"save_mean", W, kF32, kOptional}, {"save_invstd", W, kF32, kOptional}},
       check_pfn_forward, pfn_flops, nullptr, run_pfn_forward},
      {OpKind::PfnBackward, "pfn backward",
       {{"points", R, kF32}, {"w", R, kF32}, {"argmax", R, kI32}, {"dout", R, kF32}, {"dw", W, kF32},
        {"dgamma", W, kF32}, {"dbeta", W, kF32}, {"save_mean", R, kF32}, {"save_invstd", R, kF32}},
       check_pfn_backward, pfn_backward_flops, nullptr, run_pfn_backward},
      {OpKind::Scatter, "scatter forward", {{"features", R, kF32}, {"cells", R, kI32}, {"canvas", RW, kActivation}},
       check_scatter, nullptr, scatter_bytes, run_scatter},
      {OpKind::ScatterBackward, "scatter backward",
       {{"dcanvas", R, kF32}, {"cells", R, kI32}, {"dfeatures", W, kF32}}, check_scatter_backward, nullptr,
       scatter_backward_bytes, run_scatter_backward},
      {OpKind::CopyChannels, "channel copies", {{"x", R, kActivation}, {"y", RW, kActivation}}, check_copy_channels,
       nullptr, copy_channels_bytes, run_copy_channels},
      {OpKind::ExtractChannels, "channel copies", {{"y", R, kF32}, {"x", W, kF32}}, check_extract_channels, nullptr,
       extract_channels_bytes, run_extract_channels},
      {OpKind::Conv2d, "conv forward",
       {{"x", R, kF32}, {"w", R, kF32}, {"bias", R, kF32, kOptional}, {"y", W, kF32}}, check_conv2d, conv2d_flops,
       nullptr, run_conv2d},
      {OpKind::Conv2dBnReluEval, "conv+BN+ReLU eval",
       {{"x", R, kF32}, {"w", R, kF32}, {"bias", R, kF32, kOptional}, {"y", W, kF32}}, check_conv2d, conv2d_flops,
       nullptr, run_conv2d_bn_relu_eval},
      {OpKind::Conv2dBackward, "conv backward",
       {{"x", R, kF32}, {"w", R, kF32}, {"dy", R, kF32}, {"dx", W, kF32, kOptional}, {"dw", W, kF32},
        {"dbias", W, kF32, kOptional}},
       check_conv2d_backward, conv2d_backward_flops, nullptr, run_conv2d_backward, /*matrix_op=*/true},
      {OpKind::ConvTranspose2d, "convT 2x2 forward",
       {{"x", R, kF32}, {"w", R, kF32}, {"bias", R, kF32}, {"y", W, kF32}}, check_conv_transpose2d,
       conv_transpose2d_flops, nullptr, run_conv_transpose2d},
      {OpKind::ConvTranspose2dBackward, "convT 2x2 backward",
       {{"x", R, kF32}, {"w", R, kF32}, {"dy", R, kF32}, {"dx", W, kF32}, {"dw", W, kF32}, {"dbias", W, kF32}},
       check_conv_transpose2d_backward, conv_transpose2d_backward_flops, nullptr, run_conv_transpose2d_backward,
       /*matrix_op=*/true},
      {OpKind::BatchNormRelu, "batchnorm+relu forward",
       {{"x", R, kF32}, {"y", W, kF32}, {"save_mean", W, kF32, kOptional}, {"save_invstd", W, kF32, kOptional}},
       check_batchnorm_relu, nullptr, nullptr, run_batchnorm_relu},
      {OpKind::BatchNormReluBackward, "batchnorm+relu backward",
       {{"x", R, kF32}, {"y", R, kF32}, {"dy", R, kF32}, {"save_mean", R, kF32}, {"save_invstd", R, kF32},
        {"dx", W, kF32}, {"dgamma", W, kF32}, {"dbeta", W, kF32}},
       check_batchnorm_relu_backward, nullptr, nullptr, run_batchnorm_relu_backward},
      {OpKind::MaxPool2d, "maxpool forward",
       {{"x", R, kActivation}, {"y", W, kActivation}, {"argmax", W, kI32, kOptional}}, check_maxpool2d, nullptr,
       nullptr, run_maxpool2d},
      {OpKind::MaxPool2dBackward, "maxpool backward", {{"dy", R, kF32}, {"argmax", R, kI32}, {"dx", W, kF32}},
       check_maxpool2d_backward, nullptr, nullptr, run_maxpool2d_backward},
      {OpKind::UpsampleBilinear, "upsample forward", {{"x", R, kActivation}, {"y", W, kActivation}}, check_upsample,
       nullptr, nullptr, run_upsample},
      {OpKind::UpsampleBilinearBackward, "upsample backward", {{"dy", R, kF32}, {"dx", W, kF32}},
       check_upsample_backward, nullptr, nullptr, run_upsample_backward},
      {OpKind::PadConcat, "pad+concat forward",
       {{"skip", R, kActivation}, {"up", R, kActivation}, {"y", W, kActivation}}, check_pad_concat, nullptr,
       nullptr, run_pad_concat},
      {OpKind::PadConcatBackward, "pad+concat backward", {{"dy", R, kF32}, {"dskip", W, kF32}, {"dup", W, kF32}},
       check_pad_concat_backward, nullptr, nullptr, run_pad_concat_backward},
      {OpKind::AddInplace, "add (skip gradients)", {{"a", RW, kF32}, {"b", R, kF32}}, check_add_inplace, nullptr, nullptr,
       run_add_inplace},
      {OpKind::Loss, "loss",
       {{"logits", R, kF32}, {"labels", R, kU8}, {"coefficients", R, kF32}, {"dlogits", W, kF32}}, check_loss,
       nullptr, nullptr, run_loss},
      {OpKind::PrepareConvWeights, "prepared weights",
       {{"w", R, kF32}, {"bias", R, kF32, kOptional}, {"prepared", W, kPrepared}, {"prepared_bias", W, kF32},
        {"transformed", W, kFloat16, kOptional}, {"prepared_scale", W, kF32, kOptional}},
       check_prepare_conv, nullptr, nullptr, run_prepare_conv},
      {OpKind::PrepareConvTransposeWeights, "prepared weights",
       {{"w", R, kF32}, {"bias", R, kF32, kOptional}, {"prepared", W, kPrepared}, {"prepared_bias", W, kF32},
        {"transformed", W, kFloat16, kOptional}, {"prepared_scale", W, kF32, kOptional}},
       check_prepare_conv_transpose, nullptr, nullptr, run_prepare_conv_transpose},
      {OpKind::PreparedConv2d, "conv forward",
       {{"x", R, kActivation}, {"prepared", R, kPrepared}, {"prepared_bias", R, kF32},
        {"transformed", R, kFloat16, kOptional}, {"y", W, kActivation}, {"prepared_scale", R, kF32, kOptional}},
       check_prepared_conv2d, prepared_conv2d_flops, nullptr, run_prepared_conv2d, /*matrix_op=*/true},
      {OpKind::PreparedConvTranspose2d, "convT 2x2 forward",
       {{"x", R, kActivation}, {"prepared", R, kPrepared}, {"prepared_bias", R, kF32},
        {"transformed", R, kFloat16, kOptional}, {"y", W, kActivation}, {"prepared_scale", R, kF32, kOptional}},
       check_prepared_conv_transpose2d, prepared_conv_transpose2d_flops, nullptr, run_prepared_conv_transpose2d,
       /*matrix_op=*/true},
      {OpKind::Convert, "convert", {{"x", R, kF32}, {"y", W, kFloat16}}, check_convert, nullptr, nullptr,
       run_convert},
  };
  for (size_t i = 0; i < r.size(); ++i)
    PS_CHECK(static_cast<size_t>(r[i].kind) == i, "op records: entry {} ({}) out of order", i, r[i].name);
  return r;
}

// The argument structs against their records.
static_assert(sizeof(PfnForwardArgs) == 6 * sizeof(int) && sizeof(PfnBackwardArgs) == 9 * sizeof(int));
static_assert(sizeof(Conv2dBackwardArgs) == 6 * sizeof(int) && sizeof(BatchNormReluBackwardArgs) == 8 * sizeof(int));
static_assert(sizeof(PrepareConvWeightsArgs) == 6 * sizeof(int) && sizeof(PreparedConv2dArgs) == 6 * sizeof(int));

}  // namespace

const OpRecord& op_record(OpKind kind) {
  static const std::vector<OpRecord> records = make_records();
  return records.at(static_cast<size_t>(kind));
}

const char* op_name(OpKind kind) { return op_record(kind).name; }

namespace {

// The dtype that says a node's arithmetic: a convolution's compute dtype (its prepared weights'),
// else its first 16-bit argument's.
DType node_dtype(const Graph& g, const GraphNode& n) {
  if (n.op == OpKind::PreparedConv2d || n.op == OpKind::PreparedConvTranspose2d)
    return g.at(n.as<PreparedConv2dArgs>().prepared).dtype;
  if (n.op == OpKind::PrepareConvWeights || n.op == OpKind::PrepareConvTransposeWeights)
    return g.at(n.as<PrepareConvWeightsArgs>().prepared).dtype;
  if (n.compute != DType::F32) return n.compute;
  for (int id : n.args)
    if (id >= 0 && is_float16(g.at(id).dtype)) return g.at(id).dtype;
  return DType::F32;
}

}  // namespace

bool on_matrix_units(const Graph& g, const GraphNode& n) {
  const DType dtype = n.args.empty() ? DType::F32 : node_dtype(g, n);
  return !n.args.empty() && op_record(n.op).matrix_op && (is_float16(dtype) || dtype == DType::I8);
}

bool on_int8_units(const Graph& g, const GraphNode& n) {
  return on_matrix_units(g, n) && node_dtype(g, n) == DType::I8;
}

std::string op_label(const Graph& g, const GraphNode& n, Device device) {
  const OpRecord& record = op_record(n.op);
  const DType dtype = n.args.empty() ? DType::F32 : node_dtype(g, n);
  if (dtype == DType::F32) return record.name;
  const bool tensor_cores = device == Device::Cuda && on_matrix_units(g, n);
  return fmt::format("{} {}{}", record.name, dtype_name(dtype), tensor_cores ? " (tensor cores)" : "");
}

}  // namespace pillarseg
