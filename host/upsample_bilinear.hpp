// Bilinear upsampling by 2 with align_corners = true (PyTorch nn.Upsample(scale_factor=2,
// mode='bilinear', align_corners=True)): the U-Net's Up step.
//   x (B, C, H, W) -> y (B, C, 2H, 2W). Along each axis, output index d of an axis of `in` input
//   and out = 2 in output samples reads source coordinate s = d (in - 1) / (out - 1) (0 when
//   out = 1): the first and last samples of both grids coincide. With i = floor(s) and
//   l = s - i, the sample is (1 - l) x[i] + l x[min(i + 1, in - 1)], in y and then in x.
#pragma once

#include "core/tensor.hpp"

namespace pillarseg::host {

// x (B, C, H, W), H, W >= 1 -> y (B, C, 2H, 2W). y is resized and overwritten; it must not be x.
template <class T>
void upsample_bilinear_forward(const Tensor<T>& x, Tensor<T>& y);

// dy (B, C, 2H, 2W) -> dx (B, C, H, W): each output's gradient is spread over its four source
// pixels with the forward's weights. dx is resized and overwritten; it must not be dy.
template <class T>
void upsample_bilinear_backward(const Tensor<T>& dy, Tensor<T>& dx);

}  // namespace pillarseg::host
