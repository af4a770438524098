// The AVX-512 forms of three ops of half_ops.hpp on 16-bit activations (BF16 or FP16 bits): the
// 2x2 max-pool, the bilinear x2 upsampling and the pillar scatter, on plain arrays, for the
// caller's thread to run over its share. Built alone with the AVX-512 flags
// (half_ops_avx512.cpp) and called by half_ops.cpp only after avx512_half_ops_available; each
// gives the bits of the scalar loop it stands for.
#pragma once

#include <cstdint>

namespace pillarseg::cpu {

// y (planes, h / 2, w / 2) = the 2x2 stride-2 max of x (planes, h, w): a greater value, or NaN,
// replaces the best so far, in the order (0, 0), (0, 1), (1, 0), (1, 1); compared as FP32, the
// winner's bits copied.
void maxpool2d_half_avx512(const std::uint16_t* x, std::int64_t planes, std::int64_t h,
                           std::int64_t w, bool bf16, std::uint16_t* y);

// The taps of bilinear x2 upsampling (core/bilinear_taps.hpp) laid out for 16 lanes. Columns:
// output block k (outputs 16 k .. 16 k + 15 of a row) reads input columns first[k] + index0 and
// first[k] + index1 (index0/1 in 0..15) with weights w0, w1 (each (blocks, 16); lanes past the
// row's end 0). Rows: output row oy reads input rows row_i0[oy], row_i1[oy] with row_w0[oy],
// row_w1[oy].
struct UpsampleTaps {
  const std::int64_t* first;
  const std::int32_t* index0;
  const std::int32_t* index1;
  const float* w0;
  const float* w1;
  const std::int64_t* row_i0;
  const std::int64_t* row_i1;
  const float* row_w0;
  const float* row_w1;
};
// Floats of scratch upsample_bilinear_half_avx512 needs for a row of in_w inputs.
std::int64_t upsample_scratch_floats(std::int64_t in_w);
// y (planes, 2 in_h, 2 in_w) = x (planes, in_h, in_w) upsampled: each input row interpolated
// along x into FP32 (w0 a + w1 b, multiplied and added separately), then output row oy =
// row_w0 top + row_w1 bottom, rounded to nearest even to the 16 bits.
void upsample_bilinear_half_avx512(const std::uint16_t* x, std::int64_t planes, std::int64_t in_h,
                                   std::int64_t in_w, const UpsampleTaps& taps, bool bf16,
                                   float* scratch, std::uint16_t* y);

// The pillar scatter in two steps. Columns: column c of the listed pillars (columns + c stride,
// one word a pillar) = their feature c rounded to nearest even, for pillars k = 0 .. count - 1 of
// the list (features + rows[k] channels, FP32).
void scatter_columns_half_avx512(const float* features, std::int64_t channels,
                                 const std::int64_t* rows, std::int64_t count, bool bf16,
                                 std::int64_t stride, std::uint16_t* columns);
// A plane: each of its `tiles` tiles of tile_length cells (the last may be shorter) zeroed, then
// column[k] written at cell cells[k] of tile t for k in [tile_start[t], tile_start[t + 1]), in
// order (a cell named twice keeps the later value).
void scatter_plane_half_avx512(const std::uint16_t* column, const std::int32_t* cells,
                               const std::int64_t* tile_start, std::int64_t tiles,
                               std::int64_t tile_length, std::int64_t plane, std::uint16_t* out);

}  // namespace pillarseg::cpu
