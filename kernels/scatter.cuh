// Pillar scatter (PointPillars PointPillarScatter) and its backward, the gather (host/scatter.hpp
// is the spec), into a band of channels of a wider canvas (the other input streams fill the rest):
//   features (P, C), cells (P, 3) int32 rows (batch index, iy, ix) -> canvas (B, Cc, H, W) with
//   canvas(b, channel0 + c, iy, ix) = features(p, c) for the pillar p at (b, iy, ix), and 0 in
//   the cells of channels [channel0, channel0 + C) that no pillar holds; channels outside the
//   band are untouched.
//   backward: d_features(p, c) = d_canvas(b, channel0 + c, iy, ix) at the pillar's cell.
// Cells come from the pillar gather: inside the canvas and unique within a batch item (checked
// there; a kernel cannot throw). A cell outside the canvas is skipped (forward) or reads 0
// (backward) rather than touching memory outside it. Every output has one writer: deterministic.
// batch_cells: the gather's cell (R, 2) rows (iy, ix) of one sample -> (R, 3) rows (sample, iy,
// ix), (-1, -1, -1) for an unused row (iy < 0), which the scatter skips (host/scatter.hpp).
// Pointers are device memory; the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"
#include "kernels/mma.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// The canvas (B, Cc, H, W) and the band [channel0, channel0 + C) that the pillars fill.
struct ScatterCanvas {
  std::int64_t batch = 0;     // B
  std::int64_t channels = 0;  // Cc, all channels of the canvas
  std::int64_t height = 0;    // H
  std::int64_t width = 0;     // W
  std::int64_t channel0 = 0;  // first channel of the pillar band
};

// features (P, C), cells (P, 3) -> canvas (B, Cc, H, W), channels [channel0, channel0 + C).
void scatter_forward(const float* features, const std::int32_t* cells, std::int64_t pillars,
                     std::int64_t channels, const ScatterCanvas& canvas_shape, float* canvas,
                     cudaStream_t stream);

// The same into a 16-bit canvas of `type` (the mixed-precision evaluation's U-Net input): each
// feature rounded to nearest even as it is stored, as to_half16 (half_ops.cuh) rounds it.
void scatter_forward_half(const float* features, const std::int32_t* cells, std::int64_t pillars,
                          std::int64_t channels, const ScatterCanvas& canvas_shape, Half16 type,
                          std::uint16_t* canvas, cudaStream_t stream);

// d_canvas (B, Cc, H, W), cells (P, 3) -> d_features (P, C) from channels [channel0, channel0 + C).
void scatter_backward(const float* d_canvas, const ScatterCanvas& canvas_shape,
                      const std::int32_t* cells, std::int64_t pillars, std::int64_t channels,
                      float* d_features, cudaStream_t stream);

// cell (R, 2) -> cells (R, 3); sample >= 0.
void batch_cells(const std::int32_t* cell, std::int64_t rows, int sample, std::int32_t* cells,
                 cudaStream_t stream);

}  // namespace pillarseg::cuda
