// MaxPool2d, kernel 2x2, stride 2, floor mode (PyTorch nn.MaxPool2d(2)): the U-Net's Down step.
//   x (B, C, H, W) -> y (B, C, H / 2, W / 2) (integer division: an odd last row or column is
//   dropped), y[b, c, oy, ox] = max of x[b, c, 2 oy + {0, 1}, 2 ox + {0, 1}].
// argmax (B, C, H / 2, W / 2) int32 holds the flat index iy * W + ix, within its input plane, of
// the element chosen. Window order is row-major; a tie keeps the first maximum; NaN propagates:
// a window with a NaN gives NaN, and its index is the last NaN's (as PyTorch's CPU kernel).
#pragma once

#include <cstdint>

#include "core/tensor.hpp"

namespace pillarseg::host {

// x (B, C, H, W) -> y (B, C, H / 2, W / 2), argmax (same shape as y) or nullptr (not needed).
// The outputs are resized and overwritten; y must not be x.
template <class T>
void maxpool2d_forward(const Tensor<T>& x, Tensor<T>& y, Tensor<int32_t>* argmax);

// dy (B, C, H / 2, W / 2), argmax from maxpool2d_forward, x_shape = (B, C, H, W) ->
// dx (B, C, H, W): dy at each window's argmax, zero elsewhere (also in a dropped odd row or
// column). dx is resized and overwritten.
template <class T>
void maxpool2d_backward(const Tensor<T>& dy, const Tensor<int32_t>& argmax, const Shape& x_shape,
                        Tensor<T>& dx);

}  // namespace pillarseg::host
