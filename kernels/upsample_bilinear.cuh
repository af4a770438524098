// Bilinear upsampling by 2, align_corners = true (PyTorch nn.Upsample(scale_factor=2,
// mode='bilinear', align_corners=True)), host/upsample_bilinear.hpp is the spec. x (B, C, H, W)
// is seen as B * C planes:
//   forward:  x (planes, H, W) -> y (planes, 2H, 2W). Along an axis of `in` input and
//             out = 2 in output samples, output d reads source s = d (in - 1) / (out - 1), from
//             x[i0] and x[min(i0 + 1, in - 1)], i0 = floor(s), weights 1 - (s - i0) and s - i0.
//   backward: dy (planes, 2H, 2W) -> dx (planes, H, W), each output's gradient spread over its
//             four sources with the forward's weights, gathered per input pixel (every dx element
//             has one writer: no atomics, deterministic).
// Pointers are device memory; the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// x (planes, height, width), height, width >= 1 -> y (planes, 2 height, 2 width); y must not
// overlap x.
void upsample_bilinear_forward(const float* x, std::int64_t planes, std::int64_t height,
                               std::int64_t width, float* y, cudaStream_t stream);

// dy (planes, 2 height, 2 width) -> dx (planes, height, width); dx must not overlap dy.
void upsample_bilinear_backward(const float* dy, std::int64_t planes, std::int64_t height,
                                std::int64_t width, float* dx, cudaStream_t stream);

}  // namespace pillarseg::cuda
