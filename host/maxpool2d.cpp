// MaxPool2d 2x2, stride 2, floor: x (B, C, H, W) -> y, argmax (B, C, H / 2, W / 2);
// backward dy (B, C, H / 2, W / 2) -> dx (B, C, H, W). One plane (b, c) per parallel item.
#include "host/maxpool2d.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>

#include "core/error.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"

namespace pillarseg::host {

template <class T>
void maxpool2d_forward(const Tensor<T>& x, Tensor<T>& y, Tensor<int32_t>* argmax) {
  op::maxpool2d(x.shape(), "maxpool2d_forward");
  PS_CHECK(x.dim(2) * x.dim(3) <= std::numeric_limits<int32_t>::max(),
           "maxpool2d_forward: an x plane of {}x{} has more elements than an int32 argmax holds",
           x.dim(2), x.dim(3));
  PS_CHECK(&y != &x, "maxpool2d_forward: the output y must be a different tensor from x");
  const int64_t planes = x.dim(0) * x.dim(1);
  const int64_t in_h = x.dim(2);
  const int64_t in_w = x.dim(3);
  const int64_t out_h = in_h / 2;
  const int64_t out_w = in_w / 2;
  y.resize_for_overwrite({x.dim(0), x.dim(1), out_h, out_w});  // every element written
  if (argmax != nullptr) argmax->resize_for_overwrite(y.shape());

  parallel_for(planes, [&](int64_t plane) {
    const T* in = x.data() + plane * in_h * in_w;
    T* out = y.data() + plane * out_h * out_w;
    int32_t* out_index = argmax != nullptr ? argmax->data() + plane * out_h * out_w : nullptr;
    for (int64_t oy = 0; oy < out_h; ++oy) {
      for (int64_t ox = 0; ox < out_w; ++ox) {
        // PyTorch's rule: start from -inf at the window's first element; take an element that
        // is greater (so ties keep the first) or NaN (so NaN wins and propagates).
        T best = -std::numeric_limits<T>::infinity();
        int64_t best_index = 2 * oy * in_w + 2 * ox;
        for (int64_t iy = 2 * oy; iy < 2 * oy + 2; ++iy) {
          for (int64_t ix = 2 * ox; ix < 2 * ox + 2; ++ix) {
            const T value = in[iy * in_w + ix];
            if (value > best || std::isnan(value)) {
              best = value;
              best_index = iy * in_w + ix;
            }
          }
        }
        out[oy * out_w + ox] = best;
        if (out_index != nullptr) out_index[oy * out_w + ox] = static_cast<int32_t>(best_index);
      }
    }
  });
}

template <class T>
void maxpool2d_backward(const Tensor<T>& dy, const Tensor<int32_t>& argmax, const Shape& x_shape,
                        Tensor<T>& dx) {
  PS_CHECK(x_shape.size() == 4 && x_shape[0] >= 0 && x_shape[1] >= 0 && x_shape[2] >= 0 &&
               x_shape[3] >= 0,
           "maxpool2d_backward: x_shape must be (B, C, H, W), got {}", shape_str(x_shape));
  const int64_t in_h = x_shape[2];
  const int64_t in_w = x_shape[3];
  const int64_t out_h = in_h / 2;
  const int64_t out_w = in_w / 2;
  const Shape y_shape = {x_shape[0], x_shape[1], out_h, out_w};
  PS_CHECK(dy.shape() == y_shape,
           "maxpool2d_backward: dy must be (B, C, H / 2, W / 2) = {} for x {}, got {}",
           shape_str(y_shape), shape_str(x_shape), shape_str(dy.shape()));
  PS_CHECK(argmax.shape() == y_shape,
           "maxpool2d_backward: argmax must be (B, C, H / 2, W / 2) = {} for x {}, got {}",
           shape_str(y_shape), shape_str(x_shape), shape_str(argmax.shape()));
  PS_CHECK(&dx != &dy, "maxpool2d_backward: the output dx must be a different tensor from dy");
  // Each index must lie in its own window: anything else is an argmax from another shape, and
  // would write outside its plane. Checked plane by plane before the plane is written; the first
  // bad element in the tensor's order is reported.
  dx.resize_for_overwrite(x_shape);  // each plane zeroed below, then its gradients added
  const int64_t planes = x_shape[0] * x_shape[1];
  const int64_t no_error = argmax.numel();
  std::atomic<int64_t> first_bad{no_error};
  parallel_for(planes, [&](int64_t plane) {
    const T* grad_out = dy.data() + plane * out_h * out_w;
    const int32_t* index = argmax.data() + plane * out_h * out_w;
    for (int64_t oy = 0; oy < out_h; ++oy)
      for (int64_t ox = 0; ox < out_w; ++ox) {
        // The window's four elements: its first, the one right of it, and the two below.
        const int64_t d = index[oy * out_w + ox] - (2 * oy * in_w + 2 * ox);
        if (d != 0 && d != 1 && d != in_w && d != in_w + 1) {
          const int64_t bad = plane * out_h * out_w + oy * out_w + ox;
          int64_t seen = first_bad.load();
          while (bad < seen && !first_bad.compare_exchange_weak(seen, bad)) {
          }
          return;
        }
      }
    T* grad_in = dx.data() + plane * in_h * in_w;
    std::fill(grad_in, grad_in + in_h * in_w, T{0});
    for (int64_t o = 0; o < out_h * out_w; ++o) grad_in[index[o]] += grad_out[o];
  });
  if (const int64_t i = first_bad.load(); i != no_error) {
    dx.set_zero();
    PS_FAIL("maxpool2d_backward: argmax element {} = {} is not in its 2x2 window at output "
            "({}, {}) of a {}x{} plane; pass the argmax that maxpool2d_forward gave for x {}",
            i, argmax[i], i / out_w % out_h, i % out_w, in_h, in_w, shape_str(x_shape));
  }
}

template void maxpool2d_forward<float>(const Tensor<float>&, Tensor<float>&, Tensor<int32_t>*);
template void maxpool2d_forward<double>(const Tensor<double>&, Tensor<double>&, Tensor<int32_t>*);
template void maxpool2d_backward<float>(const Tensor<float>&, const Tensor<int32_t>&, const Shape&,
                                        Tensor<float>&);
template void maxpool2d_backward<double>(const Tensor<double>&, const Tensor<int32_t>&,
                                         const Shape&, Tensor<double>&);

}  // namespace pillarseg::host
