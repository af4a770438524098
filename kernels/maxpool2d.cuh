// MaxPool2d, kernel 2x2, stride 2, floor mode (PyTorch nn.MaxPool2d(2)), host/maxpool2d.hpp is the
// spec. x (B, C, H, W) is seen as B * C planes:
//   forward:  x (planes, H, W) -> y (planes, H / 2, W / 2), y = max of the 2x2 window; argmax
//             (planes, H / 2, W / 2) int32 = iy * W + ix of the element chosen, within its
//             plane. Window order is row-major; ties keep the first; a NaN wins (the last NaN of
//             the window), as PyTorch.
//   backward: dy, argmax (planes, H / 2, W / 2) -> dx (planes, H, W): dy at each window's argmax,
//             0 elsewhere (also in a dropped odd last row or column). Every element of dx has one
//             writer (a gather, no atomics); an argmax outside its window routes nothing.
// Pointers are device memory; the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// x (planes, height, width) -> y, argmax (planes, height / 2, width / 2); argmax may be nullptr
// (inference). y must not overlap x.
void maxpool2d_forward(const float* x, std::int64_t planes, std::int64_t height, std::int64_t width,
                       float* y, std::int32_t* argmax, cudaStream_t stream);

// dy, argmax (planes, height / 2, width / 2) -> dx (planes, height, width), all of it written.
void maxpool2d_backward(const float* dy, const std::int32_t* argmax, std::int64_t planes,
                        std::int64_t height, std::int64_t width, float* dx, cudaStream_t stream);

}  // namespace pillarseg::cuda
