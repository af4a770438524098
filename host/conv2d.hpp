// Conv2d, stride 1, square kernel k, zero padding `pad` on every side (PyTorch nn.Conv2d with
// stride 1, dilation 1, groups 1): the U-Net's 3x3 (pad 1) and 1x1 (pad 0) convolutions.
//   x (B, I, H, W), w (O, I, k, k), bias (O) -> y (B, O, Ho, Wo),
//   Ho = H + 2 pad - k + 1, Wo = W + 2 pad - k + 1,
//   y[b, o, oy, ox] = bias[o] + sum_{i,ky,kx} w[o, i, ky, kx] x[b, i, oy + ky - pad, ox + kx - pad]
// with x = 0 outside the image. Optional tensors are pointers (nullptr: absent / not needed);
// std::type_identity_t keeps T deduced from the other arguments, so a plain nullptr compiles.
#pragma once

#include <type_traits>

#include "core/tensor.hpp"

namespace pillarseg::host {

// x (B, I, H, W), w (O, I, k, k), bias (O) or nullptr (no bias) -> y (B, O, Ho, Wo).
// y is resized and overwritten; it must not be x.
template <class T>
void conv2d_forward(const Tensor<T>& x, const Tensor<T>& w,
                    const std::type_identity_t<Tensor<T>>* bias, int pad, Tensor<T>& y);

// Gradients of the loss given dy = dL/dy (B, O, Ho, Wo):
//   dx (B, I, H, W), dw (O, I, k, k), db (O); each may be nullptr when it is not needed.
// The gradients requested are resized and overwritten (not accumulated).
template <class T>
void conv2d_backward(const Tensor<T>& x, const Tensor<T>& w, const Tensor<T>& dy, int pad,
                     std::type_identity_t<Tensor<T>>* dx, std::type_identity_t<Tensor<T>>* dw,
                     std::type_identity_t<Tensor<T>>* db);

}  // namespace pillarseg::host
