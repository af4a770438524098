// Bilinear x2 upsampling, align_corners = true: x (B, C, H, W) -> y (B, C, 2H, 2W), and its
// backward dy (B, C, 2H, 2W) -> dx (B, C, H, W). The interpolation is separable: each output row
// and each output column has two source taps and weights, computed once per axis; one plane
// (b, c) per parallel item, so the backward's scatter-add within a plane runs in a fixed order.
#include "host/upsample_bilinear.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "core/bilinear_taps.hpp"
#include "core/error.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"

namespace pillarseg::host {
namespace {

// Sample at output index d of an axis: (1 - lambda) in[i0] + lambda in[i1].
template <class T>
using Tap = BilinearTap<T>;

// The taps of the `out` output samples of an axis with `in` input samples (core/bilinear_taps.hpp).
template <class T>
std::vector<Tap<T>> axis_taps(int64_t in, int64_t out) {
  std::vector<Tap<T>> taps(static_cast<size_t>(out));
  for (int64_t d = 0; d < out; ++d) taps[static_cast<size_t>(d)] = bilinear_tap<T>(d, in, out);
  return taps;
}

}  // namespace

template <class T>
void upsample_bilinear_forward(const Tensor<T>& x, Tensor<T>& y) {
  op::upsample_bilinear(x.shape(), "upsample_bilinear_forward");
  PS_CHECK(&y != &x, "upsample_bilinear_forward: the output y must be a different tensor from x");
  const int64_t in_h = x.dim(2);
  const int64_t in_w = x.dim(3);
  const int64_t out_h = 2 * in_h;
  const int64_t out_w = 2 * in_w;
  const std::vector<Tap<T>> rows = axis_taps<T>(in_h, out_h);
  const std::vector<Tap<T>> cols = axis_taps<T>(in_w, out_w);
  y.resize_for_overwrite({x.dim(0), x.dim(1), out_h, out_w});  // every element written

  parallel_for(x.dim(0) * x.dim(1), [&](int64_t plane) {
    const T* in = x.data() + plane * in_h * in_w;
    T* out = y.data() + plane * out_h * out_w;
    for (int64_t oy = 0; oy < out_h; ++oy) {
      const Tap<T>& r = rows[static_cast<size_t>(oy)];
      const T* top = in + r.i0 * in_w;
      const T* bottom = in + r.i1 * in_w;
      for (int64_t ox = 0; ox < out_w; ++ox) {
        const Tap<T>& c = cols[static_cast<size_t>(ox)];
        out[oy * out_w + ox] = r.w0 * (c.w0 * top[c.i0] + c.w1 * top[c.i1]) +
                               r.w1 * (c.w0 * bottom[c.i0] + c.w1 * bottom[c.i1]);
      }
    }
  });
}

template <class T>
void upsample_bilinear_backward(const Tensor<T>& dy, Tensor<T>& dx) {
  PS_CHECK(dy.rank() == 4 && dy.dim(2) >= 2 && dy.dim(3) >= 2 && dy.dim(2) % 2 == 0 &&
               dy.dim(3) % 2 == 0,
           "upsample_bilinear_backward: dy must be (B, C, 2H, 2W) with H, W >= 1, got shape {}",
           shape_str(dy.shape()));
  PS_CHECK(&dx != &dy,
           "upsample_bilinear_backward: the output dx must be a different tensor from dy");
  const int64_t out_h = dy.dim(2);
  const int64_t out_w = dy.dim(3);
  const int64_t in_h = out_h / 2;
  const int64_t in_w = out_w / 2;
  const std::vector<Tap<T>> rows = axis_taps<T>(in_h, out_h);
  const std::vector<Tap<T>> cols = axis_taps<T>(in_w, out_w);
  dx.resize_for_overwrite({dy.dim(0), dy.dim(1), in_h, in_w});  // each plane zeroed below

  parallel_for(dy.dim(0) * dy.dim(1), [&](int64_t plane) {
    const T* grad_out = dy.data() + plane * out_h * out_w;
    T* grad_in = dx.data() + plane * in_h * in_w;
    std::fill(grad_in, grad_in + in_h * in_w, T{0});
    for (int64_t oy = 0; oy < out_h; ++oy) {
      const Tap<T>& r = rows[static_cast<size_t>(oy)];
      T* top = grad_in + r.i0 * in_w;
      T* bottom = grad_in + r.i1 * in_w;
      for (int64_t ox = 0; ox < out_w; ++ox) {
        const Tap<T>& c = cols[static_cast<size_t>(ox)];
        const T g = grad_out[oy * out_w + ox];
        top[c.i0] += r.w0 * c.w0 * g;
        top[c.i1] += r.w0 * c.w1 * g;
        bottom[c.i0] += r.w1 * c.w0 * g;
        bottom[c.i1] += r.w1 * c.w1 * g;
      }
    }
  });
}

template void upsample_bilinear_forward<float>(const Tensor<float>&, Tensor<float>&);
template void upsample_bilinear_forward<double>(const Tensor<double>&, Tensor<double>&);
template void upsample_bilinear_backward<float>(const Tensor<float>&, Tensor<float>&);
template void upsample_bilinear_backward<double>(const Tensor<double>&, Tensor<double>&);

}  // namespace pillarseg::host
