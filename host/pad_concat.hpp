// The U-Net Up join (milesial's Up.forward): zero-pad the upsampled `up` to the skip
// connection's size, then concatenate channels [skip, up].
//   skip (B, Cs, H, W), up (B, Cu, h, w) with h <= H, w <= W -> y (B, Cs + Cu, H, W),
//   y[:, :Cs] = skip, y[:, Cs:] = up placed at row top = (H - h) / 2, column left = (W - w) / 2,
// zeros around it: F.pad(up, [diffX // 2, diffX - diffX // 2, diffY // 2, diffY - diffY // 2]).
#pragma once

#include <type_traits>

#include "core/tensor.hpp"

namespace pillarseg::host {

// skip (B, Cs, H, W), up (B, Cu, h, w) -> y (B, Cs + Cu, H, W). y is resized and overwritten; it
// must be neither input.
template <class T>
void pad_concat_forward(const Tensor<T>& skip, const Tensor<T>& up, Tensor<T>& y);

// dy (B, Cs + Cu, H, W) -> d_skip (B, Cs, H, W) = dy[:, :Cs] and d_up (B, Cu, h, w) = dy[:, Cs:]
// cropped to where up was placed; skip_shape and up_shape are the forward's input shapes. Either
// output may be nullptr (not needed); those requested are resized and overwritten.
// (std::type_identity_t keeps T deduced from dy, so a plain nullptr compiles.)
template <class T>
void pad_concat_backward(const Tensor<T>& dy, const Shape& skip_shape, const Shape& up_shape,
                         std::type_identity_t<Tensor<T>>* d_skip,
                         std::type_identity_t<Tensor<T>>* d_up);

}  // namespace pillarseg::host
