// U-Net Up join: skip (B, Cs, H, W) and up (B, Cu, h, w) -> y (B, Cs + Cu, H, W) = [skip,
// zero-padded up]; backward splits dy (B, Cs + Cu, H, W) into d_skip and the cropped d_up.
// One output plane (b, channel) per parallel item.
#include "host/pad_concat.hpp"

#include <algorithm>
#include <cstdint>

#include "core/error.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"

namespace pillarseg::host {
namespace {

// Where up (B, Cu, h, w) sits inside the (H, W) output: rows [top, top + h), columns
// [left, left + w).
struct Placement {
  int64_t batch = 0;
  int64_t skip_channels = 0;
  int64_t up_channels = 0;
  int64_t height = 0;  // H
  int64_t width = 0;   // W
  int64_t up_height = 0;
  int64_t up_width = 0;
  int64_t top = 0;
  int64_t left = 0;
};

Placement place(const char* caller, const Shape& skip, const Shape& up) {
  op::pad_concat(skip, up, caller);
  Placement p;
  p.batch = skip[0];
  p.skip_channels = skip[1];
  p.up_channels = up[1];
  p.height = skip[2];
  p.width = skip[3];
  p.up_height = up[2];
  p.up_width = up[3];
  p.top = (p.height - p.up_height) / 2;
  p.left = (p.width - p.up_width) / 2;
  return p;
}

}  // namespace

template <class T>
void pad_concat_forward(const Tensor<T>& skip, const Tensor<T>& up, Tensor<T>& y) {
  const Placement p = place("pad_concat_forward", skip.shape(), up.shape());
  PS_CHECK(&y != &skip && &y != &up,
           "pad_concat_forward: the output y must be a different tensor from skip and up");
  const int64_t channels = p.skip_channels + p.up_channels;
  const int64_t plane_size = p.height * p.width;
  y.resize_for_overwrite({p.batch, channels, p.height, p.width});  // every plane written below

  parallel_for(p.batch * channels, [&](int64_t plane) {
    const int64_t b = plane / channels;
    const int64_t c = plane % channels;
    T* out = y.data() + plane * plane_size;
    if (c < p.skip_channels) {
      const T* in = skip.data() + (b * p.skip_channels + c) * plane_size;
      std::copy(in, in + plane_size, out);
      return;
    }
    // The padding zero, the rows of up copied into it.
    if (p.up_height < p.height || p.up_width < p.width) std::fill(out, out + plane_size, T{0});
    const T* in = up.data() + (b * p.up_channels + c - p.skip_channels) * p.up_height * p.up_width;
    for (int64_t r = 0; r < p.up_height; ++r) {
      std::copy(in + r * p.up_width, in + (r + 1) * p.up_width,
                out + (p.top + r) * p.width + p.left);
    }
  });
}

template <class T>
void pad_concat_backward(const Tensor<T>& dy, const Shape& skip_shape, const Shape& up_shape,
                         std::type_identity_t<Tensor<T>>* d_skip,
                         std::type_identity_t<Tensor<T>>* d_up) {
  const Placement p = place("pad_concat_backward", skip_shape, up_shape);
  const Shape y_shape = {p.batch, p.skip_channels + p.up_channels, p.height, p.width};
  PS_CHECK(dy.shape() == y_shape,
           "pad_concat_backward: dy must be (B, Cs + Cu, H, W) = {} for skip {} and up {}, got {}",
           shape_str(y_shape), shape_str(skip_shape), shape_str(up_shape), shape_str(dy.shape()));
  PS_CHECK(d_skip != &dy && d_up != &dy,
           "pad_concat_backward: the outputs d_skip, d_up must be different tensors from dy");
  const int64_t channels = p.skip_channels + p.up_channels;
  const int64_t plane_size = p.height * p.width;
  // Every element of both is written below.
  if (d_skip != nullptr) d_skip->resize_for_overwrite(skip_shape);
  if (d_up != nullptr) d_up->resize_for_overwrite(up_shape);

  parallel_for(p.batch * channels, [&](int64_t plane) {
    const int64_t b = plane / channels;
    const int64_t c = plane % channels;
    const T* grad_out = dy.data() + plane * plane_size;
    if (c < p.skip_channels) {
      if (d_skip == nullptr) return;
      std::copy(grad_out, grad_out + plane_size,
                d_skip->data() + (b * p.skip_channels + c) * plane_size);
      return;
    }
    if (d_up == nullptr) return;
    T* grad_up =
        d_up->data() + (b * p.up_channels + c - p.skip_channels) * p.up_height * p.up_width;
    for (int64_t r = 0; r < p.up_height; ++r) {
      const T* row = grad_out + (p.top + r) * p.width + p.left;
      std::copy(row, row + p.up_width, grad_up + r * p.up_width);
    }
  });
}

template void pad_concat_forward<float>(const Tensor<float>&, const Tensor<float>&, Tensor<float>&);
template void pad_concat_forward<double>(const Tensor<double>&, const Tensor<double>&,
                                         Tensor<double>&);
template void pad_concat_backward<float>(const Tensor<float>&, const Shape&, const Shape&,
                                         Tensor<float>*, Tensor<float>*);
template void pad_concat_backward<double>(const Tensor<double>&, const Shape&, const Shape&,
                                          Tensor<double>*, Tensor<double>*);

}  // namespace pillarseg::host
