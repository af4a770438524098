// ConvTranspose2d with a 2x2 kernel and stride 2 (PyTorch nn.ConvTranspose2d(I, O, 2, stride=2)),
// the upsampling of the U-Net's transposed-convolution variant:
//   x (B, I, H, W), w (I, O, 2, 2), bias (O) -> y (B, O, 2H, 2W),
//   y[b, o, 2 h + dy, 2 w + dx] = bias[o] + sum_i x[b, i, h, w] w[i, o, dy, dx].
#pragma once

#include <type_traits>

#include "core/tensor.hpp"

namespace pillarseg::host {

// x (B, I, H, W), w (I, O, 2, 2), bias (O) or nullptr (no bias) -> y (B, O, 2H, 2W).
// y is resized and overwritten; it must not be x.
template <class T>
void conv_transpose2d_forward(const Tensor<T>& x, const Tensor<T>& w,
                              const std::type_identity_t<Tensor<T>>* bias, Tensor<T>& y);

// Gradients of the loss given dy = dL/dy (B, O, 2H, 2W):
//   dx (B, I, H, W), dw (I, O, 2, 2), db (O); each may be nullptr when it is not needed.
// The gradients requested are resized and overwritten (not accumulated).
template <class T>
void conv_transpose2d_backward(const Tensor<T>& x, const Tensor<T>& w, const Tensor<T>& dy,
                               std::type_identity_t<Tensor<T>>* dx,
                               std::type_identity_t<Tensor<T>>* dw,
                               std::type_identity_t<Tensor<T>>* db);

// The same gradients, using dy's memory as scratch: dy is overwritten (with its sub-pixel
// rearrangement), so that no second tensor of its size is allocated.
template <class T>
void conv_transpose2d_backward_overwriting_dy(const Tensor<T>& x, const Tensor<T>& w,
                                              std::type_identity_t<Tensor<T>>& dy,
                                              std::type_identity_t<Tensor<T>>* dx,
                                              std::type_identity_t<Tensor<T>>* dw,
                                              std::type_identity_t<Tensor<T>>* db);

}  // namespace pillarseg::host
