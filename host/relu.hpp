// ReLU, elementwise on a tensor of any shape: y = max(x, 0), with NaN passed through (as
// PyTorch's relu); backward dx = dy where y > 0, else 0.
#pragma once

#include "core/tensor.hpp"

namespace pillarseg::host {

// x (any shape) -> y (same shape). y may be x (in place); otherwise it is resized and overwritten.
template <class T>
void relu_forward(const Tensor<T>& x, Tensor<T>& y);

// y = relu_forward's output, dy = dL/dy (same shape) -> dx = dy * (y > 0). dx may be dy (in
// place); otherwise it is resized and overwritten.
template <class T>
void relu_backward(const Tensor<T>& y, const Tensor<T>& dy, Tensor<T>& dx);

}  // namespace pillarseg::host
