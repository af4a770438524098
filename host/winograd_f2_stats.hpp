// The transformed input of Winograd's F(2x2, 3x3) for a 3x3 pad-1 convolution, V = B^T d B per
// 4x4 input tile d, position by position: what an INT8 calibration sets the Winograd-domain input
// scales from (engine/model/calibration.hpp; the CPU's kernel that uses them is
// engine/cpu/int8_winograd.hpp).
//
// Each 2x2 output tile (ty, tx) of a plane of x (B, C, H, W) reads the 4x4 input tile at rows
// 2 ty - 1.., columns 2 tx - 1.. (0 outside the image), for the tiles_h = ceil(H / 2) x tiles_w =
// ceil(W / 2) tiles. B^T = [1 0 -1 0; 0 1 1 0; 0 -1 1 0; 0 1 0 -1]: the rows d_r are first made
// h_r = (d_r0 - d_r2, d_r1 + d_r2, d_r2 - d_r1, d_r1 - d_r3), then V[i][j] from the h of the four
// rows the same way, position p = 4 i + j; in FP32, in this order, as the kernel makes them.
#pragma once

#include <array>
#include <cstdint>

#include "core/tensor.hpp"

namespace pillarseg::host {

// max |V_p| over every tile and channel of x, for the 16 positions p.
std::array<float, 16> winograd_f2_input_absmax(const float* x, const Shape& shape);

// The percentile (0 < percentile <= 100) of |V_p| over the tiles and channels of x, per position:
// from a histogram of 4096 bins over [0, max |V_p|], the upper edge of the bin that holds the
// nearest-rank value (so within max |V_p| / 4096 above it; 100 gives the maximum exactly). NaN
// values are skipped.
std::array<float, 16> winograd_f2_input_percentiles(const float* x, const Shape& shape, double percentile);

}  // namespace pillarseg::host
