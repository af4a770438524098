// Conv2d 3x3, stride 1, pad 1 in float by Winograd's minimal filtering F(4x4, 3x3) (Lavin & Gray,
// "Fast Algorithms for Convolutional Neural Networks", 2016): the fast path of the U-Net's 3x3
// convolutions, beside host/conv2d.cpp (the reference it is tested against).
//   x (B, I, H, W), w (O, I, 3, 3) -> y (B, O, H, W),
//   y[b, o, oy, ox] = epilogue_o(sum_{i,ky,kx} w[o, i, ky, kx] x[b, i, oy + ky - 1, ox + kx - 1]),
//   epilogue_o(v) = v * scale[o] + shift[o], then max(v, 0) when relu is set,
// with x = 0 outside the image. The epilogue carries a bias (shift = bias) or an eval-mode
// BatchNorm folded to a per-channel affine map (scale = gamma / sqrt(var + eps),
// shift = (bias - mean) * scale + beta), so Conv -> BN -> ReLU is one pass over the output.
//
// Each 4x4 output tile comes from the 6x6 input tile around it:
//   Y = A^T [sum_i (G g_oi G^T) . (B^T d_i B)] A,
// 36 multiplies per tile and channel pair instead of 144, and the sum over i at each of the 36
// positions p is a matrix product M_p (O, tiles) = U_p (O, I) * V_p (I, tiles), done by Eigen.
// Results are the same for any thread count: the tiles are grouped into blocks by the shapes
// alone and every product and transform is computed by one thread in a fixed order.
#pragma once

#include <cstdint>
#include <vector>

#include "core/tensor.hpp"

namespace pillarseg::host {

// Per-output-channel map applied as each output value is written. Null pointers mean scale 1
// and shift 0.
struct ConvEpilogue {
  const float* scale = nullptr;  // (O)
  const float* shift = nullptr;  // (O)
  bool relu = false;
};

// Scratch reused across calls so that the steady state allocates nothing: the transformed
// weights U (36, O, I) and, per block of tiles, the transformed inputs V (36, I, tiles) and the
// products M (36, O, tiles) (for the weight gradient: dU, V and the transformed output
// gradient). It grows to the largest layer and keeps that size.
struct WinogradWorkspace {
  std::vector<float> weights, inputs, products;
  size_t bytes() const {
    return (weights.size() + inputs.size() + products.size()) * sizeof(float);
  }
};

// x (B, I, H, W), w (O, I, 3, 3) -> y (B, O, H, W) with the epilogue. y is resized and
// overwritten; it must not be x.
void conv3x3_winograd_forward(const Tensor<float>& x, const Tensor<float>& w,
                              const ConvEpilogue& epilogue, Tensor<float>& y,
                              WinogradWorkspace& workspace);

// The same convolution on activations stored as BF16 bits, x (B, I, H, W) -> y (B, O, H, W),
// the arithmetic in FP32: each x widened exactly as it is read, each y rounded to nearest even
// as it is written (the BF16 evaluation's convolutions where FP32 is the faster arithmetic).
void conv3x3_winograd_forward(const Tensor<std::uint16_t>& x, const Tensor<float>& w,
                              const ConvEpilogue& epilogue, Tensor<std::uint16_t>& y,
                              WinogradWorkspace& workspace);

// The input gradient of that convolution (without epilogue): dy (B, O, H, W), w (O, I, 3, 3)
// -> dx (B, I, H, W) = the correlation of dy with w flipped in y and x and its channel axes
// swapped (pad 1 again). dx is resized and overwritten.
void conv3x3_winograd_input_gradient(const Tensor<float>& dy, const Tensor<float>& w,
                                     Tensor<float>& dx, WinogradWorkspace& workspace);

// The weight gradient of that convolution: x (B, I, H, W), dy (B, O, H, W) -> dw (O, I, 3, 3),
// dw[o, i, ky, kx] = sum_{b, y, x} dy[b, o, y, x] x[b, i, y + ky - 1, x + kx - 1]. By linearity
// of the forward map, dw_oi = G^T [sum over tiles (A e_o A^T) . (B^T d_i B)] G, e_o the 4x4 tile
// of dy (zero beyond the image): 36 GEMMs (O, tiles) x (tiles, I) per block of tiles, summed
// over blocks in order. dw is resized and overwritten.
void conv3x3_winograd_weight_gradient(const Tensor<float>& x, const Tensor<float>& dy,
                                      Tensor<float>& dw, WinogradWorkspace& workspace);

}  // namespace pillarseg::host
