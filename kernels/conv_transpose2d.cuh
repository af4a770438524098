// ConvTranspose2d on the GPU with a 2x2 kernel and stride 2 (PyTorch
// nn.ConvTranspose2d(I, O, 2, stride=2)), the U-Net's transposed-convolution upsampling; the spec
// is the CPU reference host/conv_transpose2d.hpp:
//   x (B, I, H, W), w (I, O, 2, 2), bias (O) -> y (B, O, 2H, 2W),
//   y[b, o, 2 h + sy, 2 w + sx] = bias[o] + sum_i x[b, i, h, w] w[i, o, sy, sx],
// and its gradients dx (B, I, H, W), dw (I, O, 2, 2), db (O) given dy (B, O, 2H, 2W). Each pass
// is a 1x1-convolution GEMM (I -> 4 O sub-pixel channels) fused with the pixel shuffle, on the
// tiles of kernels/gemm_tile.cuh. Deterministic: the weight gradients sum over the batch in a
// fixed order, through a workspace, with no atomics.
//
// Pointers are device memory; outputs are overwritten (not accumulated) and must not overlap the
// inputs or each other; the work is queued on `stream`. Every tensor must have fewer than 2^31
// elements.
#pragma once

#include <cstddef>
#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// The sizes of one transposed convolution; batch and the channel counts may be 0.
struct ConvTranspose2dShape {
  std::int64_t batch = 0;
  std::int64_t in_channels = 0;   // I
  std::int64_t height = 0;        // H
  std::int64_t width = 0;         // W
  std::int64_t out_channels = 0;  // O

  std::int64_t out_height() const { return 2 * height; }
  std::int64_t out_width() const { return 2 * width; }
};

// x (B, I, H, W), w (I, O, 2, 2), bias (O) or nullptr (no bias) -> y (B, O, 2H, 2W).
void conv_transpose2d_forward(const float* x, const float* w, const float* bias, float* y,
                              const ConvTranspose2dShape& shape, cudaStream_t stream);

// The input gradient: dy (B, O, 2H, 2W), w (I, O, 2, 2) -> dx (B, I, H, W).
void conv_transpose2d_backward_data(const float* dy, const float* w, float* dx,
                                    const ConvTranspose2dShape& shape, cudaStream_t stream);

// The floats of workspace that conv_transpose2d_backward_weights needs for `shape` (0 for an
// empty batch): per split of the batch's pixels, one partial dw (I O 2 2) and one partial db (O).
std::size_t conv_transpose2d_backward_weights_workspace(const ConvTranspose2dShape& shape);

// The parameter gradients: x (B, I, H, W), dy (B, O, 2H, 2W) -> dw (I, O, 2, 2) and, unless db
// is nullptr, db (O). workspace: at least conv_transpose2d_backward_weights_workspace(shape)
// floats (workspace_floats says how many there are); its content on entry is not read.
void conv_transpose2d_backward_weights(const float* x, const float* dy, float* dw, float* db,
                                       const ConvTranspose2dShape& shape, float* workspace,
                                       std::size_t workspace_floats, cudaStream_t stream);

}  // namespace pillarseg::cuda
