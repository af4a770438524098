// The ops of PillarSegNet, each declared once (STYLE.md rule 14): its parameters and one shape
// function that checks its inputs and gives the output's shape, or throws pillarseg::Error with
// the message a user sees (what was expected, what was given, naming the op). The host reference
// ops (host/), the CUDA backend and the model's op graph (engine/model/graph.hpp) all call these;
// a shape rule changes here or nowhere.
//
// Every shape function takes the name of its caller last ("conv2d_backward", "CudaBackend::
// conv2d_forward"): messages begin with it, so that an error names the call that was given the
// wrong shapes.
//
// Layouts: activations (B, C, H, W); pillar tensors (P, N, 10) and (P, C); cells (P, 3) rows
// (sample, iy, ix); conv weights (O, I, k, k); transposed-conv weights (I, O, 2, 2); labels
// (B, H, W).
#pragma once

#include <cstdint>
#include <string_view>

#include "core/dtype.hpp"
#include "core/tensor.hpp"

namespace pillarseg::op {

// PFN: points (P, N, 10), weight (C, 10) -> (P, C).
Shape pfn(const Shape& points, const Shape& weight, const char* caller = "pfn");
// Scatter into channels [channel0, channel0 + C) of canvas (B, Cc, H, W): features (P, C),
// cells (P, 3). Returns the canvas's shape.
Shape scatter(const Shape& features, const Shape& cells, const Shape& canvas, int64_t channel0,
              const char* caller = "scatter");
// x (B, Cx, H, W) as channels [channel0, channel0 + Cx) of y (B, Cy, H, W). Returns y's shape.
Shape channel_band(const Shape& x, const Shape& y, int64_t channel0,
                   const char* caller = "channel copy");
// Stride-1 convolution: x (B, I, H, W), weight (O, I, k, k), padding pad >= 0 -> (B, O, H + 2 pad
// - k + 1, W + 2 pad - k + 1), each at least 1. bias, when given, (O).
Shape conv2d(const Shape& x, const Shape& weight, int pad, const Shape* bias = nullptr,
             const char* caller = "conv2d");
// Whether a convolution of `weight` (O, I, kh, kw) with `pad` is the 3x3 pad-1 form (stride 1,
// the same size out) that every Winograd path takes: the CPU's FP32 F(4x4, 3x3) and BF16 F(2x2,
// 3x3), the INT8 Winograd domain, and the calibration's Winograd-domain input scales.
inline bool winograd_3x3(const Shape& weight, int pad) {
  return weight.size() == 4 && weight[2] == 3 && weight[3] == 3 && pad == 1;
}

// ConvTranspose2d kernel 2 stride 2: x (B, I, H, W), weight (I, O, 2, 2) -> (B, O, 2 H, 2 W).
Shape conv_transpose2d(const Shape& x, const Shape& weight, const Shape* bias = nullptr,
                        const char* caller = "conv_transpose2d");
// BatchNorm over channels (axis 1) of x (B, C, ...) with per-channel parameters (C) -> x's shape.
Shape batchnorm(const Shape& x, const Shape& channel_parameter);
// MaxPool 2x2 stride 2 (floor): x (B, C, H, W) -> (B, C, H / 2, W / 2).
Shape maxpool2d(const Shape& x, const char* caller = "maxpool2d");
// Bilinear x2 upsampling (align_corners = true): x (B, C, H, W) -> (B, C, 2 H, 2 W).
Shape upsample_bilinear(const Shape& x, const char* caller = "upsample_bilinear");
// [skip, up zero-padded to skip's H, W]: skip (B, Cs, H, W), up (B, Cu, h <= H, w <= W) ->
// (B, Cs + Cu, H, W).
Shape pad_concat(const Shape& skip, const Shape& up, const char* caller = "pad_concat");
// Class ids of logits (B, K, H, W) -> (B, H, W).
Shape argmax(const Shape& logits);
// The loss of logits (B, K, H, W) against labels (B, H, W) with coefficients (K + 1), one per class
// id 0..K. Returns the logits' shape (that of their gradient).
Shape loss(const Shape& logits, const Shape& labels, const Shape& coefficients);
// a += b: b must have a's shape. Returns it.
Shape add_inplace(const Shape& a, const Shape& b);

// The 16-bit weights of a tensor-core convolution (kernels/conv2d_mma.cuh), the GEMM's K in
// tap-major order: k = t Ip + c for the kernel's spatial taps t (k k of them; one for a
// transposed convolution) and its I input channels c, Ip = I rounded up to a multiple of
// kHalf16WeightK (the kernels' K step, which so lies within one tap), zero for c >= I. The
// prepared weights are (O, k k Ip) for weight (O, I, k, k), (4 O, Ip) for a transposed one's
// (I, O, 2, 2).
inline constexpr int64_t kHalf16WeightK = 32;
int64_t half16_padded_channels(int64_t channels);
int64_t half16_weight_k(int64_t channels, int64_t taps);  // taps * Ip
Shape half16_conv_weights(const Shape& weight, bool transposed);
// The prepared weights of a convolution whose arithmetic is `dtype`: the layout above for 16-bit
// and INT8 weights; FP32 ones (a CPU's FP32 kernel inside a BF16 evaluation) keep the weight's own
// shape.
Shape prepared_conv_weights(const Shape& weight, bool transposed, DType dtype);

// Multiply-adds x 2 of the ops that do arithmetic on weights (for FLOP counts): a convolution
// of output (B, O, h, w) with weight (O, I, k, k); a transposed one of input (B, I, H, W) with
// weight (I, O, 2, 2); the PFN's linear layer on points (P, N, 10) with weight (C, 10).
double conv2d_flops(const Shape& y, const Shape& weight);
double conv_transpose2d_flops(const Shape& x, const Shape& weight);
double pfn_flops(const Shape& points, const Shape& weight);

}  // namespace pillarseg::op
