// The evaluation forward's data movement on activations stored as 16-bit floats (BF16 or FP16
// bits, kernels/mma.cuh), between the tensor-core convolutions (conv2d_mma.cuh):
//   to_half16            x (n) FP32 -> y (n), rounded to nearest even;
//   maxpool2d_half16    x (planes, H, W) -> y (planes, H / 2, W / 2), the largest of each 2 x 2
//                        window (an exact copy of one input; NaN wins as in the FP32 kernel);
//   upsample_bilinear_half16    bilinear x2, align_corners = true, the same taps as the FP32 kernel
//                        (core/bilinear_taps.hpp), computed in FP32 and rounded once;
//   pad_concat_half16    [skip, up zero-padded to skip's size] along channels (PadConcatShape);
//   copy_channels_half16 x as channels [channel0, channel0 + Cx) of y (ChannelBand).
// and the one convolution in FP32 arithmetic on them, the INT8 forward's 1 x 1 head:
//   pointwise_conv_half16  x (B, I, H, W) 16-bit, w (O, I), bias (O) -> y (B, O, H, W) FP32,
//                        y[b, o, p] = bias[o] + sum_{i ascending} w[o, i] x[b, i, p], FP32 sums
//                        (engine/cpu/pointwise_conv.hpp's order: the bias added last).
// Pointers are device memory; the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/elementwise.cuh"
#include "kernels/emu/cuda_compat.cuh"
#include "kernels/mma.cuh"
#include "kernels/pad_concat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

void to_half16(const float* x, std::int64_t n, Half16 type, std::uint16_t* y, cudaStream_t stream);
void maxpool2d_half16(const std::uint16_t* x, std::int64_t planes, std::int64_t height,
                       std::int64_t width, Half16 type, std::uint16_t* y, cudaStream_t stream);
void upsample_bilinear_half16(const std::uint16_t* x, std::int64_t planes, std::int64_t height,
                       std::int64_t width, Half16 type, std::uint16_t* y, cudaStream_t stream);
void pad_concat_half16(const std::uint16_t* skip, const std::uint16_t* up,
                       const PadConcatShape& shape, std::uint16_t* y, cudaStream_t stream);
void copy_channels_half16(const std::uint16_t* x, const ChannelBand& band, std::uint16_t* y,
                          cudaStream_t stream);
void pointwise_conv_half16(const std::uint16_t* x, Half16 type, const float* w, const float* bias,
                           std::int64_t batch, std::int64_t in_channels, std::int64_t out_channels,
                           std::int64_t plane, float* y, cudaStream_t stream);

}  // namespace pillarseg::cuda
