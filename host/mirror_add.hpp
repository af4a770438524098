// Test-time flips (SegmenterOptions::flips): the probabilities of a pass over a mirrored copy of
// the scan, mirrored back onto the scan's grid and added to a running sum.
//   sum (B, K, H, W) += x (B, K, H, W) mirrored: sum[b, k, iy, ix] += x[b, k, my, mx], my = H - 1 -
//   iy where mirror_y (the copy's y -> -y: on a grid symmetric about the sensor, the cell of row iy
//   lands in row H - 1 - iy) else iy, mx = W - 1 - ix where mirror_x else ix. One float addition
//   per element (the sum's value, then x's): the passes' order fixes the bits.
#pragma once

#include "core/tensor.hpp"

namespace pillarseg::host {

// x and sum of one shape (B, K, H, W); sum must not be x.
template <class T>
void mirror_add(const Tensor<T>& x, bool mirror_y, bool mirror_x, Tensor<T>& sum);

}  // namespace pillarseg::host
