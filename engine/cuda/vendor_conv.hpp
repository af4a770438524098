// Conv2d through NVIDIA's libraries, beside our kernels (kernels/conv2d.cuh) for comparison:
// stride 1, square kernel k, zero padding `pad`, the shapes of conv2d.cuh:
//   x (B, I, H, W), w (O, I, k, k), bias (O) -> y (B, O, Ho, Wo), Ho = H + 2 pad - k + 1,
//   and the gradients dx (B, I, H, W), dw (O, I, k, k), db (O) given dy (B, O, Ho, Wo).
//   CudnnConv2d:  cudnnConvolutionForward / BackwardData / BackwardFilter / BackwardBias, NCHW
//                 float, CUDNN_CROSS_CORRELATION (what a CNN calls convolution), one algorithm per
//                 shape and pass chosen on first use and kept;
//   CublasConv2d: the textbook lowering onto SGEMM: im2col + y = W cols for the forward,
//                 cols = W^T dy + col2im for dx, dw = dy cols^T and a channel sum for db; cols
//                 live in a buffer of fixed size, so a large image is lowered a band of output
//                 rows at a time.
// Both do FP32 math without TF32 by default (the comparison with our FP32 kernels is then about
// speed, not precision), both are deterministic (cuDNN algorithms are restricted to the
// deterministic ones; the cuBLAS lowering sums in a fixed order), and neither allocates inside a
// CUDA graph capture (see Conv2dEngine::forward). Pointers are device memory, outputs are
// overwritten, work is queued on `stream`; every tensor must have fewer than 2^31 elements and no
// dimension may be 0 (cuDNN rejects empty tensors; CudaBackend sends such shapes to our kernels).
//
// The engines are built only against real CUDA (pillarseg_cuda_backend, engine/cuda/
// CMakeLists.txt), never on the emulation: this header declares them for both builds, the
// definitions (vendor_conv.cu) exist only in the nvcc one.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>

#include "kernels/conv2d.cuh"

namespace pillarseg::inline PILLARSEG_CUDA_NAMESPACE {

// Which implementation runs CudaBackend's Conv2d (ConvTranspose2d is always ours).
enum class ConvolutionImpl {
  Own,     // kernels/conv2d.cu
  Cudnn,   // cuDNN (CudnnConv2d)
  Cublas,  // im2col + cuBLAS SGEMM (CublasConv2d)
};

// "own", "cudnn", "cublas" (the --conv values) and back; parse throws pillarseg::Error naming
// the accepted values.
ConvolutionImpl parse_convolution_impl(const std::string& name);
const char* convolution_impl_name(ConvolutionImpl impl);

}  // namespace pillarseg::inline PILLARSEG_CUDA_NAMESPACE

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

struct VendorConvOptions {
  // cuDNN's and cuBLAS's default math (TF32 tensor cores on Ampere and later, about 10 mantissa
  // bits) instead of FP32 only.
  bool allow_tensor_cores = false;
  // cuDNN: choose algorithms by timing them all (cudnnFind*, which runs and allocates, so never
  // inside a graph capture) instead of by cuDNN's heuristics (cudnnGet*_v7, no device work).
  // Timings vary between runs, and so may the choice and the last bits of the results.
  bool timed_search = false;
  // cuDNN: the most workspace any algorithm may use (algorithms needing more are passed over);
  // cuBLAS: the size of the cols buffer, allocated once (at least I k k floats: one pixel's taps).
  std::size_t workspace_limit_bytes = std::size_t{256} << 20;
};

// What an engine holds and has allocated (a steady state adds nothing).
struct VendorConvStats {
  std::size_t workspace_bytes = 0;  // device scratch held now (cuBLAS: its cols and workspace)
  std::int64_t device_allocations = 0;
  std::int64_t plans = 0;  // cuDNN: descriptor sets and algorithm choices made (one per shape)
};

// One Conv2d implementation; all three passes take the shapes of kernels/conv2d.cuh. An engine's
// scratch (cuDNN workspace, cuBLAS cols) serves one stream at a time: calls on different streams
// must not overlap.
class Conv2dEngine {
 public:
  virtual ~Conv2dEngine() = default;
  virtual std::string name() const = 0;
  // `capturing`: the stream is recording a CUDA graph, so the call must not allocate or wait.
  // The graph keeps the workspace pointers it recorded; an engine therefore never frees a
  // workspace that captured work used (cuDNN chooses, while capturing, among the algorithms
  // that need no workspace; cuBLAS's buffers never move).
  virtual void forward(const float* x, const float* w, const float* bias, float* y,
                       const Conv2dShape& shape, cudaStream_t stream, bool capturing) = 0;
  virtual void backward_data(const float* dy, const float* w, float* dx, const Conv2dShape& shape,
                             cudaStream_t stream, bool capturing) = 0;
  // dw and, unless db is nullptr, db.
  virtual void backward_weights(const float* x, const float* dy, float* dw, float* db,
                                const Conv2dShape& shape, cudaStream_t stream, bool capturing) = 0;
  virtual VendorConvStats stats() const = 0;
};

// The engine for `impl` (Cudnn or Cublas), with its library handle. Throws pillarseg::Error for
// Own (that is CudaBackend's own path), and for Cudnn in a build without cuDNN.
std::unique_ptr<Conv2dEngine> make_vendor_conv2d(ConvolutionImpl impl,
                                                 const VendorConvOptions& options = {});

// The vendors' 16-bit forward, beside the tensor-core convolutions (kernels/conv2d_mma.cuh) in
// the kernel benchmarks: x (B, I, H, W), w (O, I, k, k) and y (B, O, Ho, Wo) all BF16 or FP16
// (`bf16`), FP32 accumulation, tensor-core math.
//   cuDNN: cudnnConvolutionForward with the fastest algorithm cudnnFind* times (chosen, and its
//     workspace allocated, at the first call of a shape);
//   cuBLAS: the convolution's implicit GEMM as an explicit one, D (O x B Ho Wo) = W (O x I k k)
//     cols (I k k x B Ho Wo) by cublasGemmEx, on a cols buffer filled once (the GEMM alone: a
//     lower bound of what an im2col convolution costs).
class HalfConvPeer {
 public:
  virtual ~HalfConvPeer() = default;
  virtual std::string name() const = 0;
  virtual void forward(const std::uint16_t* x, const std::uint16_t* w, std::uint16_t* y, const Conv2dShape& shape,
                       cudaStream_t stream) = 0;
};
// impl Cudnn or Cublas; throws pillarseg::Error for Own and for Cudnn without cuDNN.
std::unique_ptr<HalfConvPeer> make_vendor_half_conv(ConvolutionImpl impl, bool bf16);

}  // namespace pillarseg::cuda
