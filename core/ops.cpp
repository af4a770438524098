#include "core/ops.hpp"

#include <algorithm>
#include <string>

#include "core/error.hpp"

namespace pillarseg::op {

namespace {

void require_rank(const char* op, const char* what, const Shape& shape, size_t rank,
                  const char* layout) {
  PS_CHECK(shape.size() == rank, "{}: {} must be {}, got shape {}", op, what, layout,
           shape_str(shape));
}

}  // namespace

Shape pfn(const Shape& points, const Shape& weight, const char* caller) {
  require_rank(caller, "points", points, 3, "(P, N, 10)");
  require_rank(caller, "weight", weight, 2, "(C, 10)");
  PS_CHECK(points[2] == 10 && weight[1] == 10,
           "{}: points (P, N, 10) and weight (C, 10) hold 10 features a point, got {} and {}",
           caller, shape_str(points), shape_str(weight));
  return {points[0], weight[0]};
}

Shape scatter(const Shape& features, const Shape& cells, const Shape& canvas, int64_t channel0,
              const char* caller) {
  require_rank(caller, "features", features, 2, "(P, C)");
  require_rank(caller, "canvas", canvas, 4, "(B, Cc, H, W)");
  PS_CHECK(cells == (Shape{features[0], 3}),
           "{}: cells must be ({}, 3) rows (sample, iy, ix), got {}", caller, features[0],
           shape_str(cells));
  PS_CHECK(channel0 >= 0 && channel0 + features[1] <= canvas[1],
           "{}: the pillar channels [{}, {}) lie outside the canvas's {} channels", caller,
           channel0, channel0 + features[1], canvas[1]);
  return canvas;
}

Shape channel_band(const Shape& x, const Shape& y, int64_t channel0, const char* caller) {
  require_rank(caller, "x", x, 4, "(B, Cx, H, W)");
  require_rank(caller, "y", y, 4, "(B, Cy, H, W)");
  PS_CHECK(x[0] == y[0] && x[2] == y[2] && x[3] == y[3] && channel0 >= 0 && channel0 + x[1] <= y[1],
           "{}: x {} does not fit at channel {} of y {}", caller, shape_str(x), channel0,
           shape_str(y));
  return y;
}

Shape conv2d(const Shape& x, const Shape& weight, int pad, const Shape* bias, const char* caller) {
  require_rank(caller, "x", x, 4, "(B, I, H, W)");
  PS_CHECK(weight.size() == 4 && weight[2] == weight[3] && weight[2] >= 1,
           "{}: w must be (O, I, k, k) with a square kernel k >= 1, got shape {}", caller,
           shape_str(weight));
  PS_CHECK(weight[1] == x[1], "{}: w {} expects I = {} input channels, but x {} has {} channels",
           caller, shape_str(weight), weight[1], shape_str(x), x[1]);
  PS_CHECK(pad >= 0, "{}: pad must be >= 0, got {}", caller, pad);
  const int64_t k = weight[2];
  const Shape y{x[0], weight[0], x[2] + 2 * pad - k + 1, x[3] + 2 * pad - k + 1};
  PS_CHECK(x[2] >= 1 && x[3] >= 1 && y[2] >= 1 && y[3] >= 1,
           "{}: a {}x{} kernel with pad {} needs an image of at least {}x{} (H x W), got {}x{}",
           caller, k, k, pad, std::max<int64_t>(1, k - 2 * pad), std::max<int64_t>(1, k - 2 * pad),
           x[2], x[3]);
  PS_CHECK(bias == nullptr || *bias == (Shape{weight[0]}),
           "{}: bias must be (O) = ({}) for w {}, got shape {}", caller, weight[0],
           shape_str(weight), bias ? shape_str(*bias) : std::string());
  return y;
}

Shape conv_transpose2d(const Shape& x, const Shape& weight, const Shape* bias,
                        const char* caller) {
  require_rank(caller, "x", x, 4, "(B, I, H, W)");
  PS_CHECK(x[2] >= 1 && x[3] >= 1, "{}: x must have H, W >= 1, got shape {}", caller, shape_str(x));
  PS_CHECK(weight.size() == 4 && weight[2] == 2 && weight[3] == 2,
           "{}: w must be (I, O, 2, 2) (PyTorch ConvTranspose2d layout), got shape {}", caller,
           shape_str(weight));
  PS_CHECK(weight[0] == x[1], "{}: w {} expects I = {} input channels, but x {} has {} channels",
           caller, shape_str(weight), weight[0], shape_str(x), x[1]);
  PS_CHECK(bias == nullptr || *bias == (Shape{weight[1]}),
           "{}: bias must be (O) = ({}) for w {}, got shape {}", caller, weight[1],
           shape_str(weight), bias ? shape_str(*bias) : std::string());
  return {x[0], weight[1], 2 * x[2], 2 * x[3]};
}

Shape batchnorm(const Shape& x, const Shape& channel_parameter) {
  PS_CHECK(x.size() >= 2, "batchnorm: x must be (B, C, ...), got shape {}", shape_str(x));
  PS_CHECK(channel_parameter == (Shape{x[1]}),
           "batchnorm: per-channel parameters must be ({}) for x {}, got {}", x[1], shape_str(x),
           shape_str(channel_parameter));
  return x;
}

Shape maxpool2d(const Shape& x, const char* caller) {
  require_rank(caller, "x", x, 4, "(B, C, H, W)");
  return {x[0], x[1], x[2] / 2, x[3] / 2};
}

Shape upsample_bilinear(const Shape& x, const char* caller) {
  require_rank(caller, "x", x, 4, "(B, C, H, W)");
  PS_CHECK(x[2] >= 1 && x[3] >= 1, "{}: x must have H, W >= 1, got shape {}", caller, shape_str(x));
  return {x[0], x[1], 2 * x[2], 2 * x[3]};
}

Shape pad_concat(const Shape& skip, const Shape& up, const char* caller) {
  require_rank(caller, "skip", skip, 4, "(B, Cs, H, W)");
  require_rank(caller, "up", up, 4, "(B, Cu, h, w)");
  PS_CHECK(up[0] == skip[0], "{}: skip {} and up {} must have the same batch size", caller,
           shape_str(skip), shape_str(up));
  PS_CHECK(
      up[2] <= skip[2] && up[3] <= skip[3],
      "{}: up {} must be at most as large as skip {} (h <= H, w <= W), to be zero-padded to it",
      caller, shape_str(up), shape_str(skip));
  return {skip[0], skip[1] + up[1], skip[2], skip[3]};
}

Shape argmax(const Shape& logits) {
  require_rank("argmax", "logits", logits, 4, "(B, K, H, W)");
  return {logits[0], logits[2], logits[3]};
}

Shape loss(const Shape& logits, const Shape& labels, const Shape& coefficients) {
  require_rank("loss", "logits", logits, 4, "(B, K, H, W)");
  PS_CHECK(labels == argmax(logits), "loss: labels must be {}, got {}", shape_str(argmax(logits)),
           shape_str(labels));
  PS_CHECK(coefficients == (Shape{logits[1] + 1}),
           "loss: coefficients (one per class id, 0 unused) must be ({}), got {}", logits[1] + 1,
           shape_str(coefficients));
  return logits;
}

Shape add_inplace(const Shape& a, const Shape& b) {
  PS_CHECK(a == b, "add: b must have a's shape {}, got {}", shape_str(a), shape_str(b));
  return a;
}

int64_t half16_padded_channels(int64_t channels) {
  return (channels + kHalf16WeightK - 1) / kHalf16WeightK * kHalf16WeightK;
}
int64_t half16_weight_k(int64_t channels, int64_t taps) {
  return taps * half16_padded_channels(channels);
}

Shape half16_conv_weights(const Shape& weight, bool transposed) {
  PS_CHECK(weight.size() == 4, "16-bit weights: weight must have 4 dimensions, got shape {}", shape_str(weight));
  if (transposed) return {4 * weight[1], half16_weight_k(weight[0], 1)};
  return {weight[0], half16_weight_k(weight[1], weight[2] * weight[3])};
}

Shape prepared_conv_weights(const Shape& weight, bool transposed, DType dtype) {
  if (dtype != DType::F32) return half16_conv_weights(weight, transposed);
  PS_CHECK(weight.size() == 4, "FP32 prepared weights: weight must have 4 dimensions, got shape {}", shape_str(weight));
  return weight;
}

double conv2d_flops(const Shape& y, const Shape& weight) {
  return 2.0 * static_cast<double>(shape_numel(y)) *
         static_cast<double>(weight[1] * weight[2] * weight[3]);
}

double conv_transpose2d_flops(const Shape& x, const Shape& weight) {
  return 2.0 * static_cast<double>(shape_numel(x)) *
         static_cast<double>(weight[1] * weight[2] * weight[3]);
}

double pfn_flops(const Shape& points, const Shape& weight) {
  return 2.0 * static_cast<double>(shape_numel(points)) * static_cast<double>(weight[0]);
}

}  // namespace pillarseg::op
