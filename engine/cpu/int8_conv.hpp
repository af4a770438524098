// The CPU's INT8 evaluation convolutions (DESIGN.md section 10): FP32 weights with BatchNorm
// folded in -> per-output-channel symmetric INT8 weights, prepared once; at run time the FP32 or
// BF16 input (B, I, H, W) is quantized with a per-tensor scale into the convolution's own
// workspace, multiplied into INT32 accumulators, and the epilogue writes FP32 or BF16 (B, O, ...).
//
// The contract, the same for every kernel choice (the tests hold each to it bit for bit):
//   weights   sw[o] = max |w[o, ...]| / 127 (FP32; 0 for an all-zero channel), qw = clamp(
//             round_half_even(w / sw[o]), -127, 127) (0 where sw[o] is 0);
//   input     q = clamp(round_half_even(x * r), -127, 127) with r = 1 / sx rounded to FP32 once
//             (a multiply, not a division: the same bits in the vector and scalar code, half the
//             cost), NaN -> 0, +-inf -> +-127; the padding is q = 0;
//   or, for an input the caller knows is non-negative (non_negative: ReLU outputs and what
//             max-pooling, bilinear upsampling and concatenation make of them), the whole code
//             range on [0, 255 sx]: q = clamp(round_half_even(x * r), 0, 255), NaN -> 0,
//             negatives and -inf -> 0, +inf -> 255; the padding q = 0. Twice the resolution of the
//             signed rule at the same clip value (sx = clip / 255 instead of clip / 127);
//   products  acc = sum over (tap, channel) of q qw in INT32, wrapping (the U-Net's layers stay far
//             from 2^31: even the unsigned sum below is at most 9 * 1536 * 255 * 127 < 2^29);
//   epilogue  y = act(fma(float(acc), sx * sw[o], bias[o])), float() and the product sx * sw[o]
//             each rounded to nearest even, act the ReLU max(y, 0) (NaN -> 0) or none, then BF16
//             rounded to nearest even (weights::float_to_bf16_bits) or FP32.
//
// The instructions multiply unsigned by signed bytes, so the signed input is stored shifted, u = q
// + 128 (the padding 128), and the prepared weights carry comp[o] = 128 sum qw[o, ...] to take
// off: acc = sum u qw - comp[o]; the non-negative input is stored as it is, u = q (the padding 0),
// and nothing is taken off: acc = sum u qw. Kernels, chosen at run time:
//   Vnni         AVX512-VNNI VPDPBUSD (int8_microkernel.hpp; AVX512F, BW, VL and VNNI: Cascade
//                Lake, Ice Lake and later, Zen 4);
//   Amx          AMX-INT8 TDPBSUD on tiles (int8_amx.hpp; Sapphire Rapids and later), the
//                epilogue and the quantization on AVX-512 as in Vnni;
//   Emulated, AmxEmulated  the same code on exact scalar models of the instructions
//                (int8_isa_emulated.hpp): the tests' way to check both on any CPU (slow).
// Vnni and Emulated share a weight packing, Amx and AmxEmulated another (prepare for the family
// the forward will use). Threads: num_threads(); results do not depend on the thread count.
// The windows of a scan's empty cells (no input pixel unlike a reference pixel) skip their
// products on every kernel and give the same bits (int8_microkernel.hpp, "Idle windows").
// And for the 3x3 pad-1 convolutions, Winograd-domain INT8 F(2x2, 3x3) on Vnni (below): 2.25x
// fewer multiply-adds for its transforms' cost and a larger error (about 1.4x the direct one's);
// bench_int8_conv measures both per layer. Its transformed input is signed whatever x is, so it has
// no non-negative mode.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/ops.hpp"
#include "core/tensor.hpp"
#include "engine/backend/backend.hpp"
#include "engine/cpu/cpu_features.hpp"

namespace pillarseg::cpu {

bool int8_amx_family(Int8Kernels kernels);  // Amx or AmxEmulated

// The quantization rules above, one value at a time (the kernels' reference).
std::int8_t quantize_int8(float x, float reciprocal);    // reciprocal = 1 / sx rounded to FP32
std::uint8_t quantize_uint8(float x, float reciprocal);  // the non-negative input's rule
float int8_weight_scale(float max_abs);                  // max_abs / 127

// A prepared convolution: `weight` is the FP32 weight's shape, (O, I, k, k) or transposed (I, O,
// 2, 2). The GEMM's columns are the output channels o, or for the transposed convolution n = 4 o
// + 2 dy + dx (the output pixel (2 row + dy, 2 col + dx) of input pixel (row, col)).
struct Int8ConvWeights {
  Int8Kernels packed_for = Int8Kernels::Vnni;  // the family its packing serves
  Shape weight;
  bool transposed = false;
  std::int64_t columns = 0;
  std::vector<std::int8_t> q;              // qw in the FP32 weight's layout and shape
  std::vector<float> scale;                // sw, (O)
  std::vector<float> bias;                 // (columns)
  std::vector<std::int32_t> compensation;  // (columns): 128 times the sum of the column's qw
  AlignedVector<std::int8_t> packed;       // qw laid out for the micro-kernel (int8_conv.cpp)
};

// w (O, I, k, k), bias (O) (BatchNorm already folded into both) -> `out`, packed for the family of
// `kernels`.
void prepare_int8_conv(Int8Kernels kernels, const Ref& w, const Ref& bias, Int8ConvWeights& out);
// w (I, O, 2, 2), bias (O) of the transposed 2x2 stride-2 convolution -> `out`.
void prepare_int8_conv_transpose(Int8Kernels kernels, const Ref& w, const Ref& bias,
                                 Int8ConvWeights& out);

// The quantized input in the micro-kernel's layout, a band of rows for each thread, kept by the
// caller between calls so that the steady state allocates nothing (it only grows).
struct Int8ConvWorkspace {
  AlignedVector<std::uint8_t> x;
  // The idle windows' state (int8_microkernel.hpp): the bands' busy bits, each image's reference
  // quads, whether its padding differs from them, and its idle accumulators (B, columns).
  std::vector<std::uint64_t> busy;
  std::vector<std::uint32_t> reference;
  std::vector<std::uint8_t> padding_busy;
  std::vector<std::int32_t> idle;
};

// x (B, I, H, W) FP32 or BF16 (x.half) -> y (B, O, Ho, Wo) = act(conv(x, w) + bias), stride 1,
// zero padding `pad`, FP32 or BF16 (y.half), for the input scale sx > 0, x quantized by the
// non-negative rule where non_negative, else the signed one (the same weights serve both).
void int8_conv2d_forward(Int8Kernels kernels, const ActRef& x, float sx, bool non_negative,
                         const Int8ConvWeights& w, int pad, bool relu, const ActRef& y,
                         Int8ConvWorkspace& workspace);
// x (B, I, H, W) -> y (B, O, 2H, 2W), the transposed 2x2 stride-2 convolution, no activation.
void int8_conv_transpose2d_forward(Int8Kernels kernels, const ActRef& x, float sx,
                                   bool non_negative, const Int8ConvWeights& w, const ActRef& y,
                                   Int8ConvWorkspace& workspace);

// Winograd-domain INT8 F(2x2, 3x3) for the 3x3 pad-1 convolutions (int8_winograd.hpp has the
// arithmetic), on Vnni or Emulated (the AMX family is refused): weights U = G g G^T per position p
// and output channel, quantized with su[p][o] = max over the input channels |U| / 127; the
// transformed input V_p with its own scale sv[p] per position (int8_winograd_input_absmax gives the
// maxima a calibration takes them from).
struct Int8WinogradWeights {
  Shape weight;                            // (O, I, 3, 3)
  std::vector<std::int8_t> q;              // qU (16, O, I)
  std::vector<float> scale;                // su (16, O)
  std::vector<float> bias;                 // (O)
  std::vector<std::int32_t> compensation;  // (16, O rounded up to 8): 128 sum over I of qU
  AlignedVector<std::int8_t> packed;       // qU (16, O / 8, I / 4, 8, 4), zero padded
};
void prepare_int8_winograd(const Ref& w, const Ref& bias, Int8WinogradWeights& out);

struct Int8WinogradWorkspace {
  AlignedVector<std::uint8_t> v;
  AlignedVector<float> m;
  AlignedVector<std::int16_t> x16;
};

// The 16-bit input transform's constants (int8_winograd.hpp) for the 16 calibrated scales sv > 0:
// s16 = min(max_p sv[p] / 64, min_p sv[p]) (the first unless the positions' scales differ 64-fold,
// where inputs beyond 8191 s16 clip), r16 = 1 / s16 rounded to FP32, multiplier[p] = round(2^15
// s16 / sv[p]) within [1, 32767], and the effective scale sv_eff[p] = s16 2^15 / multiplier[p]
// (rounded to FP32) that the products are dequantized with.
struct Int8WinogradInputScales {
  float r16 = 0.0f;
  std::int16_t multiplier[16] = {};
  float sv_eff[16] = {};
};
Int8WinogradInputScales int8_winograd_input_scales(const float* sv);

// x (B, I, H, W) FP32 or BF16 -> y (B, O, H, W) FP32 or BF16, for the 16 input scales sv > 0.
void int8_winograd_forward(Int8Kernels kernels, const ActRef& x, const float* sv,
                           const Int8WinogradWeights& w, bool relu, const ActRef& y,
                           Int8WinogradWorkspace& workspace);
// max |V_p| over x's tiles and channels for the 16 positions p (V in FP32 as the kernel makes it).
void int8_winograd_input_absmax(const ActRef& x, float* absmax);

// Whether a 3x3 pad-1 INT8 convolution of `weight` (O, I, 3, 3) whose input has Winograd-domain
// scales runs in that domain on `kernels`: never on the AMX family (its direct tiles are faster
// than VNNI's Winograd products); on Vnni and its model by `rule` (cpu_features.hpp), whose
// default takes the layers with at least 256 input or output channels: there the 2.25x fewer
// products outweigh the transforms (bench_int8_conv, docs/benchmarks.md#int8). The 64-128 channel
// layers stay direct for accuracy: with the 16-bit input transform Winograd is as fast or faster
// there too, but every layer in the Winograd domain put the demo model's real-scan arg-max
// agreement with FP32 at 97.4-98.2% (the direct layers: 99.2-99.4%; the target is 99.0%).
inline bool int8_winograd_runs(Int8Kernels kernels, const Shape& weight, Int8WinogradRule rule) {
  if (int8_amx_family(kernels) || weight.size() != 4 || weight[2] != 3 || weight[3] != 3)
    return false;
  if (rule != Int8WinogradRule::Pays) return rule == Int8WinogradRule::Always;
  return weight[0] >= 256 || weight[1] >= 256;
}

// Whether an INT8 convolution's forward runs in the Winograd domain, as `bench` reports it: what
// CpuBackend's preparation (int8_winograd_runs, not transposed) and forward (the 3x3 pad-1 form,
// op::winograd_3x3, and an input calibrated with Winograd-domain scales, Int8Input::winograd)
// choose together.
inline bool int8_forward_in_winograd(Int8Kernels kernels, const Shape& weight, int pad,
                                     bool transposed, bool winograd_scales, Int8WinogradRule rule) {
  return !transposed && winograd_scales && op::winograd_3x3(weight, pad) &&
         int8_winograd_runs(kernels, weight, rule);
}

}  // namespace pillarseg::cpu
