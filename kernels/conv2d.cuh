// Conv2d on the GPU, stride 1, square kernel k, zero padding `pad` on every side (PyTorch
// nn.Conv2d with stride 1, dilation 1, groups 1); the spec is the CPU reference host/conv2d.hpp:
//   x (B, I, H, W), w (O, I, k, k), bias (O) -> y (B, O, Ho, Wo),
//   Ho = H + 2 pad - k + 1, Wo = W + 2 pad - k + 1,
//   y[b, o, oy, ox] = bias[o] + sum_{i,ky,kx} w[o, i, ky, kx] x[b, i, oy + ky - pad, ox + kx - pad]
// with x = 0 outside the image, and its gradients dx (B, I, H, W), dw (O, I, k, k), db (O) given
// dy (B, O, Ho, Wo). Every pass is a tiled implicit GEMM (kernels/gemm_tile.cuh) that gathers
// the im2col taps on the fly, with no im2col buffer. Results are deterministic: the same inputs
// give the same bits on every run (the weight gradients sum over the batch in a fixed order,
// through a workspace, with no atomics).
//
// Pointers are device memory; outputs are overwritten (not accumulated) and must not overlap the
// inputs or each other; the work is queued on `stream`. Every tensor must have fewer than 2^31
// elements.
#pragma once

#include <cstddef>
#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// The sizes of one convolution; batch, in_channels and out_channels may be 0 (nothing to
// compute, or, for dw and db, all zeros).
struct Conv2dShape {
  std::int64_t batch = 0;
  std::int64_t in_channels = 0;   // I
  std::int64_t height = 0;        // H
  std::int64_t width = 0;         // W
  std::int64_t out_channels = 0;  // O
  std::int64_t kernel = 1;        // k
  std::int64_t pad = 0;

  std::int64_t out_height() const { return height + 2 * pad - kernel + 1; }
  std::int64_t out_width() const { return width + 2 * pad - kernel + 1; }
};

// x (B, I, H, W), w (O, I, k, k), bias (O) or nullptr (no bias) -> y (B, O, Ho, Wo).
void conv2d_forward(const float* x, const float* w, const float* bias, float* y,
                    const Conv2dShape& shape, cudaStream_t stream);

// The input gradient: dy (B, O, Ho, Wo), w (O, I, k, k) -> dx (B, I, H, W).
void conv2d_backward_data(const float* dy, const float* w, float* dx, const Conv2dShape& shape,
                          cudaStream_t stream);

// The floats of workspace that conv2d_backward_weights needs for `shape` (0 for an empty batch):
// per split of the batch's pixels, one partial dw (O I k k) and one partial db (O).
std::size_t conv2d_backward_weights_workspace(const Conv2dShape& shape);

// The parameter gradients: x (B, I, H, W), dy (B, O, Ho, Wo) -> dw (O, I, k, k) and, unless db
// is nullptr, db (O). workspace: at least conv2d_backward_weights_workspace(shape) floats
// (workspace_floats says how many there are); its content on entry is not read.
void conv2d_backward_weights(const float* x, const float* dy, float* dw, float* db,
                             const Conv2dShape& shape, float* workspace,
                             std::size_t workspace_floats, cudaStream_t stream);

}  // namespace pillarseg::cuda
