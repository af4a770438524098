// ReLU forward y = max(x, 0) (NaN passed through) and backward dx = dy * (y > 0), elementwise on
// tensors of any shape, in parallel chunks.
#include "host/relu.hpp"

#include <cmath>
#include <cstdint>

#include "core/error.hpp"
#include "core/parallel.hpp"

namespace pillarseg::host {

template <class T>
void relu_forward(const Tensor<T>& x, Tensor<T>& y) {
  // In place (y is x) keeps the storage; otherwise y gets x's shape.
  if (&y != &x) y.resize(x.shape());
  const T* in = x.data();
  T* out = y.data();
  parallel_chunks(x.numel(), [&](int64_t begin, int64_t end, int) {
    for (int64_t i = begin; i < end; ++i)
      out[i] = (in[i] > T{0} || std::isnan(in[i])) ? in[i] : T{0};
  });
}

template <class T>
void relu_backward(const Tensor<T>& y, const Tensor<T>& dy, Tensor<T>& dx) {
  PS_CHECK(dy.shape() == y.shape(), "relu_backward: dy must have the shape of y {}, got {}",
           shape_str(y.shape()), shape_str(dy.shape()));
  PS_CHECK(&dx != &y, "relu_backward: the output dx must be a different tensor from y");
  if (&dx != &dy) dx.resize(y.shape());
  const T* out = y.data();
  const T* grad_out = dy.data();
  T* grad_in = dx.data();
  parallel_chunks(y.numel(), [&](int64_t begin, int64_t end, int) {
    for (int64_t i = begin; i < end; ++i) grad_in[i] = out[i] > T{0} ? grad_out[i] : T{0};
  });
}

template void relu_forward<float>(const Tensor<float>&, Tensor<float>&);
template void relu_forward<double>(const Tensor<double>&, Tensor<double>&);
template void relu_backward<float>(const Tensor<float>&, const Tensor<float>&, Tensor<float>&);
template void relu_backward<double>(const Tensor<double>&, const Tensor<double>&, Tensor<double>&);

}  // namespace pillarseg::host
