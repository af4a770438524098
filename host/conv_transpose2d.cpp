// ConvTranspose2d, kernel 2x2, stride 2: x (B, I, H, W), w (I, O, 2, 2), bias (O) ->
// y (B, O, 2H, 2W); backward dy (B, O, 2H, 2W) -> dx, dw, db.
//
// With stride equal to the kernel size the output windows do not overlap: output pixel
// (2h + dy, 2w + dx) depends on input pixel (h, w) only. The op is therefore a 1x1 convolution
// from I to 4 O channels, channel o * 4 + dy * 2 + dx holding sub-pixel (dy, dx) of output
// channel o, followed by a pixel shuffle that moves each sub-pixel channel to its place; its
// backward is the inverse shuffle followed by the 1x1 convolution's backward (host/conv2d).
// Sub-pixel channels o * 4 .. o * 4 + 3 fill exactly the bytes of output channel o, so both
// shuffles run in place, one channel at a time: the sub-pixel tensor is y's (or dy's) memory.
#include "host/conv_transpose2d.hpp"

#include <algorithm>
#include <cstdint>
#include <type_traits>
#include <vector>

#include "core/error.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"
#include "host/conv2d.hpp"

namespace pillarseg::host {
namespace {

constexpr int64_t kSubPixels = 4;  // (dy, dx) in {0, 1}^2, index dy * 2 + dx

// Checks x, w and bias (op::conv_transpose2d); `caller` names the calling op in messages.
template <class T>
void check_args(const char* caller, const Tensor<T>& x, const Tensor<T>& w,
                const std::type_identity_t<Tensor<T>>* bias) {
  op::conv_transpose2d(x.shape(), w.shape(), bias != nullptr ? &bias->shape() : nullptr, caller);
}

// w (I, O, 2, 2) -> the equivalent 1x1 convolution weight (4 O, I, 1, 1):
// pointwise[o * 4 + s, i] = w[i, o, s / 2, s % 2].
template <class T>
Tensor<T> pointwise_weight(const Tensor<T>& w) {
  const int64_t in_channels = w.dim(0);
  const int64_t out_channels = w.dim(1);
  Tensor<T> pointwise({out_channels * kSubPixels, in_channels, 1, 1});
  for (int64_t i = 0; i < in_channels; ++i)
    for (int64_t o = 0; o < out_channels; ++o)
      for (int64_t s = 0; s < kSubPixels; ++s)
        pointwise(o * kSubPixels + s, i, 0, 0) = w(i, o, s / 2, s % 2);
  return pointwise;
}

// Rearranges each of the `planes` chunks of 4 H W values of `data` in place through a copy of
// one chunk: to_output (the forward's shuffle, adding offset(plane) to every value)
//   chunk[(2 h + s / 2) * 2 W + 2 w + s % 2] = copy[s * H W + h * W + w] + offset(plane),
// or back (the backward's inverse shuffle, no offset)
//   chunk[s * H W + h * W + w] = copy[(2 h + s / 2) * 2 W + 2 w + s % 2].
template <class T, class Offset>
void shuffle_in_place(T* data, int64_t planes, int64_t height, int64_t width, bool to_output,
                      const Offset& offset) {
  const int64_t sub_plane = height * width;
  const int64_t chunk_size = kSubPixels * sub_plane;
  parallel_chunks(planes, [&](int64_t begin, int64_t end, int) {
    std::vector<T> copy(static_cast<size_t>(chunk_size));
    for (int64_t plane = begin; plane < end; ++plane) {
      T* chunk = data + plane * chunk_size;
      std::copy(chunk, chunk + chunk_size, copy.begin());
      const T add = to_output ? offset(plane) : T{0};
      for (int64_t s = 0; s < kSubPixels; ++s)
        for (int64_t h = 0; h < height; ++h)
          for (int64_t c = 0; c < width; ++c) {
            const int64_t sub = s * sub_plane + h * width + c;
            const int64_t out = (2 * h + s / 2) * 2 * width + 2 * c + s % 2;
            if (to_output) {
              chunk[out] = copy[static_cast<size_t>(sub)] + add;
            } else {
              chunk[sub] = copy[static_cast<size_t>(out)];
            }
          }
    }
  });
}

}  // namespace

template <class T>
void conv_transpose2d_forward(const Tensor<T>& x, const Tensor<T>& w,
                              const std::type_identity_t<Tensor<T>>* bias, Tensor<T>& y) {
  check_args("conv_transpose2d_forward", x, w, bias);
  PS_CHECK(&y != &x && &y != &w && &y != bias,
           "conv_transpose2d_forward: the output y must be a different tensor from x, w, bias");
  const int64_t batch = x.dim(0);
  const int64_t height = x.dim(2);
  const int64_t width = x.dim(3);
  const int64_t out_channels = w.dim(1);

  y.resize({batch, out_channels, 2 * height, 2 * width});
  Tensor<T> sub_pixels =
      Tensor<T>::view(y.data(), {batch, out_channels * kSubPixels, height, width});
  conv2d_forward(x, pointwise_weight(w), nullptr, 0, sub_pixels);
  shuffle_in_place(
      y.data(), batch * out_channels, height, width, /*to_output=*/true,
      [&](int64_t plane) { return bias != nullptr ? (*bias)[plane % out_channels] : T{0}; });
}

template <class T>
void conv_transpose2d_backward(const Tensor<T>& x, const Tensor<T>& w, const Tensor<T>& dy,
                               std::type_identity_t<Tensor<T>>* dx,
                               std::type_identity_t<Tensor<T>>* dw,
                               std::type_identity_t<Tensor<T>>* db) {
  Tensor<T> scratch = dy;
  conv_transpose2d_backward_overwriting_dy(x, w, scratch, dx, dw, db);
}

template <class T>
void conv_transpose2d_backward_overwriting_dy(const Tensor<T>& x, const Tensor<T>& w,
                                              std::type_identity_t<Tensor<T>>& dy,
                                              std::type_identity_t<Tensor<T>>* dx,
                                              std::type_identity_t<Tensor<T>>* dw,
                                              std::type_identity_t<Tensor<T>>* db) {
  check_args("conv_transpose2d_backward", x, w, nullptr);
  const int64_t batch = x.dim(0);
  const int64_t height = x.dim(2);
  const int64_t width = x.dim(3);
  const int64_t in_channels = w.dim(0);
  const int64_t out_channels = w.dim(1);
  const Shape y_shape = {batch, out_channels, 2 * height, 2 * width};
  PS_CHECK(dy.shape() == y_shape,
           "conv_transpose2d_backward: dy must have the output shape {}, got {}",
           shape_str(y_shape), shape_str(dy.shape()));
  for (const Tensor<T>* grad : {dx, dw, db}) {
    PS_CHECK(grad == nullptr || (grad != &x && grad != &w && grad != &dy),
             "conv_transpose2d_backward: the gradients dx, dw, db must be different tensors "
             "from x, w, dy");
  }

  if (db != nullptr) {
    db->resize({out_channels});
    for (int64_t b = 0; b < batch; ++b)
      for (int64_t o = 0; o < out_channels; ++o)
        for (int64_t p = 0; p < 4 * height * width; ++p)
          (*db)[o] += dy[(b * out_channels + o) * 4 * height * width + p];
  }
  if (dx == nullptr && dw == nullptr) return;

  // Inverse pixel shuffle: d_sub_pixels[b, o * 4 + s, h, w] = dy[b, o, 2 h + s / 2, 2 w + s % 2].
  shuffle_in_place(dy.data(), batch * out_channels, height, width, /*to_output=*/false,
                   [](int64_t) { return T{0}; });
  const Tensor<T> d_sub_pixels =
      Tensor<T>::view(dy.data(), {batch, out_channels * kSubPixels, height, width});

  Tensor<T> d_pointwise;  // (4 O, I, 1, 1)
  conv2d_backward(x, pointwise_weight(w), d_sub_pixels, 0, dx,
                  dw != nullptr ? &d_pointwise : nullptr, nullptr);
  if (dw != nullptr) {
    dw->resize(w.shape());
    for (int64_t i = 0; i < in_channels; ++i)
      for (int64_t o = 0; o < out_channels; ++o)
        for (int64_t s = 0; s < kSubPixels; ++s)
          (*dw)(i, o, s / 2, s % 2) = d_pointwise(o * kSubPixels + s, i, 0, 0);
  }
}

template void conv_transpose2d_forward<float>(const Tensor<float>&, const Tensor<float>&,
                                              const Tensor<float>*, Tensor<float>&);
template void conv_transpose2d_forward<double>(const Tensor<double>&, const Tensor<double>&,
                                               const Tensor<double>*, Tensor<double>&);
template void conv_transpose2d_backward<float>(const Tensor<float>&, const Tensor<float>&,
                                               const Tensor<float>&, Tensor<float>*, Tensor<float>*,
                                               Tensor<float>*);
template void conv_transpose2d_backward<double>(const Tensor<double>&, const Tensor<double>&,
                                                const Tensor<double>&, Tensor<double>*,
                                                Tensor<double>*, Tensor<double>*);
template void conv_transpose2d_backward_overwriting_dy<float>(const Tensor<float>&,
                                                              const Tensor<float>&, Tensor<float>&,
                                                              Tensor<float>*, Tensor<float>*,
                                                              Tensor<float>*);
template void conv_transpose2d_backward_overwriting_dy<double>(const Tensor<double>&,
                                                               const Tensor<double>&,
                                                               Tensor<double>&, Tensor<double>*,
                                                               Tensor<double>*, Tensor<double>*);

}  // namespace pillarseg::host
