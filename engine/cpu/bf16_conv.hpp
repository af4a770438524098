// The CPU backend's BF16 evaluation convolutions (--precision bf16 on --device cpu): the
// contract of kernels/conv2d_mma.cuh (prepared weights w16 (O, Kp) or (4 O, Kp) in BF16 with the
// eval BatchNorm folded in, FP32 bias, FP32 accumulation, BF16 or FP32 outputs rounded once), on
// our own AVX512_BF16 kernels, chosen at run time: a direct micro-kernel (bf16_microkernel.hpp)
// for any kernel size and the transposed 2x2, and Winograd F(2x2, 3x3) (bf16_winograd.hpp) for
// the 3x3 pad-1 convolutions, which the CPU backend runs.
//
// On CPUs with AMX-BF16 (Sapphire Rapids and later, Linux 5.16+), the Winograd convolutions'
// products run on the AMX tiles (bf16_amx.hpp), the transforms and the other convolutions on
// AVX512_BF16.
//
// Bf16Kernels::Emulated runs the same micro-kernel on an exact scalar model of the instructions
// (bf16_isa_emulated.hpp), AmxEmulated the AMX path on its model: the tests' way to check them on
// CPUs without AVX512_BF16 or AMX (slow).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/tensor.hpp"
#include "engine/backend/backend.hpp"
#include "engine/cpu/cpu_features.hpp"

namespace pillarseg::cpu {

// Whether `kernels` run the 3 x 3 pad-1 convolution of weight (O, I, 3, 3) by Winograd F(2x2,
// 3x3) faster than the FP32 Winograd F(4x4, 3x3) on the same BF16 activations, on a CPU whose
// VDPBF16PS does (`dot_outpaces_fma`, cpu_features.hpp) or does not outpace its FMAs.
bool bf16_winograd_pays(Bf16Kernels kernels, bool dot_outpaces_fma, const Shape& weight);

// The host version of the CUDA backend's weight preparation, the same arithmetic: w (O, I, k,
// k) [, bias] [, eval BatchNorm] -> w16 (O, Kp) rounded to `p`, bias_out (O); transposed: w (I,
// O, 2, 2) -> w16 (4 O, Kp) with row o 4 + dy 2 + dx, bias_out (4 O).
void prepare_conv_weights(const Ref& w, const Ref* bias, const BatchNormRefs* bn, Precision p,
                          HRef& w16, Ref& bias_out);
void prepare_conv_transpose_weights(const Ref& w, const Ref* bias, Precision p, HRef& w16,
                                    Ref& bias_out);

// x (B, I, H, W) BF16 -> y (B, O, Ho, Wo) = act(conv(x, w16) + bias_out) for `weight` (O, I, k,
// k) and `pad` (stride 1), FP32 or BF16 (y.dtype). Threads: num_threads(); results do not depend
// on the thread count.
void conv2d_forward(Bf16Kernels kernels, const HRef& x, const HRef& w16, const Ref& bias_out,
                    const Shape& weight, int pad, bool relu, const TensorRef& y);
// Scratch of the Winograd convolution, kept by its owner (the CPU backend) between calls so that
// the steady state allocates nothing: the transformed weights and each thread's blocks.
struct Bf16WinogradWorkspace {
  std::vector<std::uint16_t> u, v;
  std::vector<float> m;
};

// The same convolution for 3 x 3 kernels with pad 1 by Winograd F(2x2, 3x3)
// (bf16_winograd.hpp): x (B, I, H, W) BF16, the same w16 and bias_out -> y (B, O, H, W). `u`:
// the transformed weights that winograd_transform_weights made from w16 for these kernels, or
// nullptr to make them here (in the workspace).
void conv3x3_winograd_forward(Bf16Kernels kernels, const HRef& x, const HRef& w16,
                              const std::uint16_t* u, const Ref& bias_out, const Shape& weight,
                              bool relu, const TensorRef& y, Bf16WinogradWorkspace& workspace);
// The Winograd-transformed weights of a 3 x 3 convolution of weight (O, I, 3, 3): U = G g G^T
// of each prepared BF16 kernel g of w16 (in double, rounded once), laid out for `kernels` (AMX's
// tiles pad the channel pairs and rows): their element count, and U itself.
std::int64_t winograd_weight_elements(Bf16Kernels kernels, const Shape& weight);
void winograd_transform_weights(Bf16Kernels kernels, const HRef& w16, const Shape& weight,
                                std::uint16_t* u);
// x (B, I, H, W) BF16 -> y (B, O, 2H, 2W), the transposed 2x2 stride-2 convolution for `weight`
// (I, O, 2, 2).
void conv_transpose2d_forward(Bf16Kernels kernels, const HRef& x, const HRef& w16,
                               const Ref& bias_out, const Shape& weight, const TensorRef& y);

}  // namespace pillarseg::cpu
