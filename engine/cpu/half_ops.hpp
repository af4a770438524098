// The CPU backend's 16-bit activations' data movement (--precision bf16 on --device cpu): the ops
// of kernels/half_ops.cuh on host memory, bit for bit the same, for BF16 and FP16 bits; and the
// rounding to 16 bits that the BF16 convolutions' weight preparation shares (bf16_conv.hpp).
#pragma once

#include <cstdint>

#include "core/tensor.hpp"
#include "engine/backend/backend.hpp"

namespace pillarseg::cpu {

// v rounded to nearest even to p's 16 bits (BF16 or FP16).
std::uint16_t to_bits(float v, Precision p);
// Throws unless p is BF16 or FP16 (`op` names the caller).
void require_half(const char* op, Precision p);

// Which kernels run the max-pool, the upsampling and the scatter below: the scalar loops of
// half_ops.cpp, or their AVX-512 forms (half_ops_avx512.hpp, AVX512F, BW and VL), the same bits.
enum class HalfOpsKernels { Scalar, Avx512 };
// Avx512 where avx512_half_ops_available (cpu_features.hpp), else Scalar.
HalfOpsKernels native_half_ops_kernels();

// The 16-bit data movement (kernels/half_ops.cuh), for BF16 and FP16 bits. `kernels` Avx512 where
// this CPU or build cannot run it is an error.
void to_half(const Ref& x, Precision p, HRef& y);
void maxpool2d_half(const HRef& x, Precision p, HRef& y,
                    HalfOpsKernels kernels = native_half_ops_kernels());
void upsample_bilinear_half(const HRef& x, Precision p, HRef& y,
                            HalfOpsKernels kernels = native_half_ops_kernels());
void pad_concat_half(const HRef& skip, const HRef& up, HRef& y);
void copy_channels_half(const HRef& x, int channel0, HRef& y);
// The pillar scatter into channels [channel0, channel0 + C) of a 16-bit canvas (B, Cc, H, W):
// the band zeroed, then each feature rounded to nearest even at its cell, a cell named twice
// keeping the later row's; a cell outside the canvas (an inert row's (-1, -1, -1)) is skipped
// (kernels/scatter.cuh).
void scatter_half(const Ref& features, const IRef& cells, int channel0, Precision p, HRef& canvas,
                  HalfOpsKernels kernels = native_half_ops_kernels());

}  // namespace pillarseg::cpu
