// The CPU's 1 x 1 convolution in FP32 arithmetic on activations of either width: the head of
// the INT8 and BF16 evaluation forwards (FP32 prepared weights, Backend::prepared_conv_dtype),
// which reads the U-Net's last output as it was stored (BF16, widened as read) rather than a
// converted FP32 copy of it.
//   x (B, I, H, W) FP32 or BF16, w (O, I), bias (O) -> y (B, O, H, W) FP32 or BF16,
//   y[b, o, p] = act(bias[o] + sum_{i ascending} w[o, i] x[b, i, p])
// with one FP32 sum per output element, its products added in input-channel order from 0 (each
// multiply and add fused where the compiler fuses them), the bias added last, ReLU where asked,
// and BF16 outputs rounded to nearest even once: the result does not depend on the thread count.
#pragma once

#include "engine/backend/backend.hpp"

namespace pillarseg::cpu {

// `op` names the caller in errors (shapes, dtypes: x and y F32 or BF16).
void pointwise_conv_forward(const char* op, const TensorRef& x, const Ref& w, const Ref& bias, bool relu,
                            const TensorRef& y);

}  // namespace pillarseg::cpu
