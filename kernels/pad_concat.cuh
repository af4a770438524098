// The U-Net Up join (host/pad_concat.hpp is the spec): zero-pad the upsampled `up` to the skip
// connection's size, then concatenate channels [skip, up]:
//   skip (B, Cs, H, W), up (B, Cu, h, w), h <= H, w <= W -> y (B, Cs + Cu, H, W),
//   y[:, :Cs] = skip, y[:, Cs:] = up at row top = (H - h) / 2, column left = (W - w) / 2, zeros
//   around it (F.pad(up, [diffX // 2, diffX - diffX // 2, diffY // 2, diffY - diffY // 2])).
//   backward: dy (B, Cs + Cu, H, W) -> d_skip = dy[:, :Cs], d_up = dy[:, Cs:] cropped to where
//   up was placed.
// Pure data movement: exact and deterministic. Pointers are device memory; the work is queued on
// `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

struct PadConcatShape {
  std::int64_t batch = 0;          // B
  std::int64_t skip_channels = 0;  // Cs
  std::int64_t up_channels = 0;    // Cu
  std::int64_t height = 0;         // H, of skip and y
  std::int64_t width = 0;          // W
  std::int64_t up_height = 0;      // h <= H
  std::int64_t up_width = 0;       // w <= W
};

// skip (B, Cs, H, W), up (B, Cu, h, w) -> y (B, Cs + Cu, H, W), all of it written; y overlaps
// neither input.
void pad_concat_forward(const float* skip, const float* up, const PadConcatShape& shape, float* y,
                        cudaStream_t stream);

// dy (B, Cs + Cu, H, W) -> d_skip (B, Cs, H, W), d_up (B, Cu, h, w); either may be nullptr (not
// needed). Neither overlaps dy.
void pad_concat_backward(const float* dy, const PadConcatShape& shape, float* d_skip, float* d_up,
                         cudaStream_t stream);

}  // namespace pillarseg::cuda
