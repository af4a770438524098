// Convolutions on the tensor cores: implicit GEMM with mma.sync m16n8k16 in BF16 or FP16
// (kernels/mma.cuh), FP32 accumulation, fragments loaded with ldmatrix. The forward (evaluation,
// and training without the BatchNorm fold) of two kinds, and their training gradients (below):
//   - a stride-1 convolution x (B, I, H, W), weight (O, I, k, k), pad -> y (B, O, Ho, Wo), as the
//     GEMM D (pixels x O) = A (pixels x I k k, the im2col taps gathered on the fly) B, with an
//     eval BatchNorm folded into the weights and the bias, and an optional ReLU;
//   - ConvTranspose2d kernel 2 stride 2, x (B, I, H, W), weight (I, O, 2, 2) -> y (B, O, 2H, 2W),
//     as D (pixels x 4 O) = x^T B, each column (o, dy, dx) written to its sub-pixel.
// The weights go through prepare_*_weights once per set of values: rounded to the 16-bit type
// (after the BatchNorm scale is multiplied in, in FP32), laid out (N, Kp) with K tap-major,
// column t Ip + c for tap t and input channel c, the channels padded to Ip, a multiple of 32,
// with zeros (op::half16_weight_k: Kp = k k Ip, or Ip for the transposed kind), and the bias
// (with the BatchNorm shift) in FP32. Activations are FP32 (rounded to the 16-bit type as they are
// staged in shared memory) or already 16-bit, and so is y (rounded once from the FP32 result). So y
// = act(sum_k half(w'[n, k]) half(a[m, k]) + b'[n]) with the products exact and the sum in FP32.
//
// Needs compute capability 8.0 or later on a GPU (mma_supported()); the emulation runs it
// everywhere. Pointers are device memory; the work is queued on `stream`.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

#include "kernels/conv2d.cuh"
#include "kernels/conv_transpose2d.cuh"
#include "kernels/emu/cuda_compat.cuh"
#include "kernels/mma.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// Whether the current device runs these kernels (compute capability >= 8.0; always in the
// emulation), and a sentence saying why not.
bool mma_supported(std::string* why_not = nullptr);

// Eval BatchNorm folded into a convolution: y = gamma (conv + bias - mean) / sqrt(var + eps) +
// beta. All (O), device memory; nullptr pointers throughout for no BatchNorm.
struct FoldedBatchNorm {
  const float* gamma = nullptr;
  const float* beta = nullptr;
  const float* running_mean = nullptr;
  const float* running_var = nullptr;
  float eps = 1e-5f;
};

// w (O, I, k, k) [, bias (O) or nullptr] [, BatchNorm] -> w16 (O, k k Ip) 16-bit, bias_out (O)
// FP32.
void prepare_conv_weights(const float* w, const float* bias, const FoldedBatchNorm& bn,
                          const Conv2dShape& shape, Half16 type, std::uint16_t* w16,
                          float* bias_out, cudaStream_t stream);
// The same fold in FP32, for the FP32 kernels (conv2d.cuh) on 16-bit activations: w (O, I, k, k)
// [, bias] [, BatchNorm] -> folded (O, I, k, k) with the scale multiplied in, bias_out (O).
void fold_conv_weights(const float* w, const float* bias, const FoldedBatchNorm& bn,
                       const Conv2dShape& shape, float* folded, float* bias_out,
                       cudaStream_t stream);
// w (I, O, 2, 2) [, bias (O)] -> w16 (4 O, Ip) with row o 4 + dy 2 + dx, bias_out (4 O).
void prepare_conv_transpose_weights(const float* w, const float* bias, std::int64_t in_channels,
                                    std::int64_t out_channels, Half16 type, std::uint16_t* w16,
                                    float* bias_out, cudaStream_t stream);

// x (B, I, H, W), prepared w16 and bias -> y (B, O, Ho, Wo), ReLU when `relu`. x and y are
// FP32 (float) or, with x_half / y_half, 16-bit values of `type` (std::uint16_t bits).
// workspace: nullptr, or *_workspace(shape) floats of device memory (0 for most shapes): with it,
// a GEMM of few tiles and a long K (the deepest layers) splits K over blocks, about 256 in all,
// whose FP32 sums a second kernel adds in split order (the same bits on every run and GPU; other
// bits than unsplit, whose sum runs in another order).
std::int64_t conv2d_mma_forward_workspace(const Conv2dShape& shape);
void conv2d_mma_forward(const void* x, bool x_half, const std::uint16_t* w16, const float* bias,
                        const Conv2dShape& shape, Half16 type, bool relu, void* y, bool y_half,
                        cudaStream_t stream, float* workspace = nullptr);
// x (B, I, H, W), prepared w16 and bias -> y (B, O, 2H, 2W); x, y, workspace as above.
std::int64_t conv_transpose2d_mma_forward_workspace(std::int64_t batch, std::int64_t in_channels,
                                                     std::int64_t height, std::int64_t width,
                                                     std::int64_t out_channels);
void conv_transpose2d_mma_forward(const void* x, bool x_half, const std::uint16_t* w16,
                                   const float* bias, std::int64_t batch, std::int64_t in_channels,
                                   std::int64_t height, std::int64_t width,
                                   std::int64_t out_channels, Half16 type, void* y, bool y_half,
                                   cudaStream_t stream, float* workspace = nullptr);

// Training gradients on the tensor cores, FP32 tensors throughout: x, dy and the weights rounded
// to `type` as they are staged, FP32 accumulation, dbias (or nullptr) summed in double from the
// FP32 dy.
//   - dx (B, I, H, W) of a stride-1 convolution = the convolution of dy (B, O, Ho, Wo) with the
//     flipped weights w16t (I, k k Op), row i column t Op + o = w[o][i][k k - 1 - t]
//     (prepare_conv_data_weights; Op = O padded to 32), padding k - 1 - pad;
//   - dw (O, I, k, k) = sum over the pixels of dy x im2col(x), split over the pixels in a fixed
//     number of parts summed in order (the same bits on every run and GPU), `workspace` of
//     conv2d_mma_backward_weights_workspace(shape) floats;
//   - the transposed 2x2: dx (B, I, H, W) from the 4 O sub-pixel values of dy (B, O, 2H, 2W) and
//     w16t (I, 4 Op), row i column s Op + o = w[i][o][s] for the sub-pixel s = 2 dy + dx;
//     dw (I, O, 2, 2).
void prepare_conv_data_weights(const float* w, const Conv2dShape& shape, Half16 type,
                               std::uint16_t* w16t, cudaStream_t stream);
// The input gradients split K as the forward does, given *_backward_data_workspace floats.
std::int64_t conv2d_mma_backward_data_workspace(const Conv2dShape& shape);
void conv2d_mma_backward_data(const float* dy, const std::uint16_t* w16t, const Conv2dShape& shape,
                              Half16 type, float* dx, cudaStream_t stream,
                              float* workspace = nullptr);
std::int64_t conv2d_mma_backward_weights_workspace(const Conv2dShape& shape);
void conv2d_mma_backward_weights(const float* x, const float* dy, const Conv2dShape& shape,
                                 Half16 type, float* dw, float* dbias, float* workspace,
                                 cudaStream_t stream);
void prepare_conv_transpose_data_weights(const float* w, const ConvTranspose2dShape& shape,
                                         Half16 type, std::uint16_t* w16t, cudaStream_t stream);
std::int64_t conv_transpose2d_mma_backward_data_workspace(const ConvTranspose2dShape& shape);
void conv_transpose2d_mma_backward_data(const float* dy, const std::uint16_t* w16t,
                                         const ConvTranspose2dShape& shape, Half16 type, float* dx,
                                         cudaStream_t stream, float* workspace = nullptr);
std::int64_t conv_transpose2d_mma_backward_weights_workspace(const ConvTranspose2dShape& shape);
void conv_transpose2d_mma_backward_weights(const float* x, const float* dy,
                                            const ConvTranspose2dShape& shape, Half16 type,
                                            float* dw, float* dbias, float* workspace,
                                            cudaStream_t stream);

// Self-checks of the fragment layouts, one warp each (tests/test_kernels_mma.cpp, on the GPU
// from the bundle): D (16 x 8) = A (16 x 16) B (16 x 8) + C, all row-major FP32, with each
// lane's registers built from A and B by the PTX ISA's formulas and its results stored by them;
// and out (32 lanes x 12 words) = what each lane's ldmatrix x4, x4.trans, x2, x2.trans return
// for the 16 x 16 matrix of 16-bit values 256 r + c.
void mma_fragment_probe(const float* a, const float* b, const float* c, Half16 type, float* d,
                        cudaStream_t stream);
void ldmatrix_probe(std::uint32_t* out, cudaStream_t stream);
// Self-check of cp.async, one warp: each lane fills its 16 bytes of three shared stages with
// 0xDEADBEEF words, copies its 16 bytes of source[s] (3 x 32 x 4 words) into stage s by
// cp_async_16 (stage 1 zero-filled: fill = false), one group each, and writes the three stages'
// words to out (32 lanes x 24 words) after cp_async_wait<2> (words 0..11) and after
// cp_async_wait<0> (12..23). `misalign` moves the destinations by 4 bytes (the emulation
// refuses that; never on a GPU, where it faults).
void cp_async_probe(const std::uint32_t* source, std::uint32_t* out, bool misalign,
                    cudaStream_t stream);

}  // namespace pillarseg::cuda
