// INT8 convolutions on the tensor cores for inference: implicit GEMM with mma.sync m16n8k32, s8 x
// s8, or u8 x s8 for non-negative activations (kernels/mma.cuh), exact 32-bit integer
// accumulation, requantization in the epilogue. The forward of the two kinds of conv2d_mma.cuh:
//   - a stride-1 convolution x (B, I, H, W), weight (O, I, k, k), pad -> y (B, O, Ho, Wo), with an
//     eval BatchNorm folded into the weights and the bias, and an optional ReLU;
//   - ConvTranspose2d kernel 2 stride 2, x (B, I, H, W), weight (I, O, 2, 2) -> y (B, O, 2H, 2W).
//
// Weights: prepare_conv_weights_s8 / prepare_conv_transpose_weights_s8 run once per set of values
// on the device and give, for the GEMM's N columns (O for a convolution; 4 O for the transposed
// kind, column 4 o + 2 dy + dx):
//   w8 (N, Kp) int8, K tap-major as the 16-bit kernels' (column t Ip + c for tap t and input
//     channel c, Ip = I padded to a multiple of 32 with zeros: Kp = op::half16_weight_k(I, k k),
//     or Ip for the transposed kind): q = clamp(rint(w' / sw), -127, 127), w' the FP32 weight
//     with the BatchNorm's scale gamma / sqrt(var + eps) multiplied in (rounded to FP32);
//   w_scale (N) FP32: sw, per output channel and symmetric, max |w'| over the channel's I k k
//     weights (transposed: I x 4) / 127; 0 for an all-zero channel (whose q are then 0);
//   bias_out (N) FP32: the bias with the BatchNorm's shift beta - scale mean.
// Activations, x and y, in one of three layouts (ActivationLayout): FP32 or BF16 planes (B, C, H,
//   W), or int8 in blocks of 32 channels. A tensor's scale s (per tensor, calibrated, > 0)
//   quantizes it as q = clamp(rint(v r), -127, 127) with r = 1 / s and v r each rounded to FP32,
//   rint to the nearest integer, ties to even: |v| beyond 127 s clamps, NaN becomes 0 (the CPU
//   backend's INT8 rule, so that both give the same bits). A multiply, not a division: q differs
//   from rint(v / s) only where v / s lies within an FP32 rounding of a half-integer. FP32 and
//   BF16 inputs are quantized as they are staged in shared memory, on every tap that reads them;
//   int8 inputs (quantize_activations_s8, or a previous layer's int8 output) are copied as they
//   are, by cp.async, which leaves the kernel no work but the tensor cores' on them.
// Non-negative activations (ActivationsS8::non_negative; the U-Net's convolution inputs are ReLU
//   outputs, max-pooled, upsampled and concatenated): FP32 or BF16 x quantized as staged to u8,
//   q = clamp(rint(v r), 0, 255) with r and v r rounded as above, NaN, negatives and -inf -> 0,
//   +inf -> 255, padding 0 (the CPU backend's unsigned rule), and multiplied by mma.sync
//   m16n8k32 .u8.s8 (activations are A, the weights B): a clip value c takes s = c / 255 rather
//   than c / 127, twice the resolution. There is no unsigned int8 layout: non_negative with an
//   S8x32 x is refused (the launchers throw).
// Output: acc = sum over K of q_w q_x in 32 bits, exact (|acc| <= 127^2 Kp, 255 127 Kp for u8 x;
//   wraps past 2^31, Kp > 133,000, 66,000 for u8 x); v = act(fma(float(acc), s, bias_out[n]))
//   with s = sx w_scale[n] rounded to FP32, act ReLU or nothing; stored as v (FP32), v rounded
//   once to BF16, or q(v) with y's scale (signed, S8x32, whatever x was).
//
// Needs compute capability 8.0 or later on a GPU (mma_supported(), conv2d_mma.cuh); the
// emulation runs it everywhere. Pointers are device memory (int8 tensors and w8 16-byte
// aligned); the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/conv2d.cuh"
#include "kernels/conv2d_mma.cuh"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// How activations (B, C, H, W) are stored: FP32 or BF16 (std::uint16_t bits) planes, or S8x32:
// int8 (B, Cp / 32, H, W, 32), Cp = C padded to 32, value (b, c, y, x) at byte ((b Cp / 32 + c /
// 32) H W + y W + x) 32 + c % 32, zeros for c >= C.
enum class ActivationLayout { F32, BF16, S8x32 };

// The bytes of an S8x32 tensor: B Cp H W.
std::int64_t activations_s8_bytes(std::int64_t batch, std::int64_t channels, std::int64_t height,
                                  std::int64_t width);
// x (B, C, H, W), F32 or BF16, with scale `scale` -> q, S8x32 (activations_s8_bytes).
void quantize_activations_s8(const void* x, ActivationLayout x_layout, float scale,
                             std::int64_t batch, std::int64_t channels, std::int64_t height,
                             std::int64_t width, std::int8_t* q, cudaStream_t stream);

// w (O, I, k, k) [, bias (O) or nullptr] [, BatchNorm] -> w8 (O, k k Ip), w_scale (O), bias_out
// (O).
void prepare_conv_weights_s8(const float* w, const float* bias, const FoldedBatchNorm& bn,
                             const Conv2dShape& shape, std::int8_t* w8, float* w_scale,
                             float* bias_out, cudaStream_t stream);
// w (I, O, 2, 2) [, bias (O)] -> w8 (4 O, Ip), w_scale (4 O) and bias_out (4 O), row 4 o + 2 dy +
// dx holding output channel o's scale and bias.
void prepare_conv_transpose_weights_s8(const float* w, const float* bias, std::int64_t in_channels,
                                       std::int64_t out_channels, std::int8_t* w8, float* w_scale,
                                       float* bias_out, cudaStream_t stream);

// One side of a convolution's activations: where, in which layout, and the scale (of x: sx; of
// y: only for S8x32, the scale it is quantized with). non_negative (x only, FP32 or BF16): x is
// quantized to u8 and multiplied as unsigned (see the top of the file); with S8x32 the launchers
// throw ("non_negative needs an FP32 or BF16 input").
struct ActivationsS8 {
  const void* data = nullptr;
  ActivationLayout layout = ActivationLayout::F32;
  float scale = 1.0f;
  bool non_negative = false;
};
struct OutputS8 {
  void* data = nullptr;
  ActivationLayout layout = ActivationLayout::F32;
  float scale = 1.0f;
};

// x (B, I, H, W), prepared w8, w_scale and bias_out -> y (B, O, Ho, Wo), ReLU when `relu`.
// workspace: nullptr, or *_workspace(shape) 32-bit integers of device memory (0 for most
// shapes): with it, a GEMM of few tiles and a long K (the deepest layers) splits K over blocks,
// about 256 in all, whose integer sums a second kernel adds; integer sums are exact, so y has the
// same bits split or not.
std::int64_t conv2d_mma_s8_forward_workspace(const Conv2dShape& shape);
void conv2d_mma_s8_forward(const ActivationsS8& x, const std::int8_t* w8, const float* w_scale,
                           const float* bias_out, const Conv2dShape& shape, bool relu,
                           const OutputS8& y, cudaStream_t stream,
                           std::int32_t* workspace = nullptr);
// x (B, I, H, W), prepared w8, w_scale, bias_out -> y (B, O, 2H, 2W); the rest as above.
std::int64_t conv_transpose2d_mma_s8_forward_workspace(std::int64_t batch,
                                                        std::int64_t in_channels,
                                                        std::int64_t height, std::int64_t width,
                                                        std::int64_t out_channels);
void conv_transpose2d_mma_s8_forward(const ActivationsS8& x, const std::int8_t* w8,
                                      const float* w_scale, const float* bias_out,
                                      std::int64_t batch, std::int64_t in_channels,
                                      std::int64_t height, std::int64_t width,
                                      std::int64_t out_channels, bool relu, const OutputS8& y,
                                      cudaStream_t stream, std::int32_t* workspace = nullptr);

// Self-check of the fragment layout, one warp (tests/test_kernels_int8.cpp, on the GPU from the
// bundle): D (16 x 8) = A (16 x 32) B (32 x 8) + C, A and B row-major int8, C and D row-major
// int32, with each lane's registers built from A and B by the PTX ISA's formulas and its results
// stored by them.
void mma_s8_fragment_probe(const std::int8_t* a, const std::int8_t* b, const std::int32_t* c,
                           std::int32_t* d, cudaStream_t stream);
// The same for mma.sync m16n8k32 .u8.s8 (the non_negative kernels'): A's bytes unsigned.
void mma_u8s8_fragment_probe(const std::uint8_t* a, const std::int8_t* b, const std::int32_t* c,
                             std::int32_t* d, cudaStream_t stream);

}  // namespace pillarseg::cuda
