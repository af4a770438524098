// Peers of kernels/conv2d.cu's forward for bench/bench_kernels_conv.cpp, built only with CUDA and
// cuDNN (bench/CMakeLists.txt adds this file and defines PILLARSEG_BENCH_CUDNN), never emulated:
//   cudnn_conv2d_forward:         cudnnConvolutionForward with the algorithm that
//                                 cudnnFindConvolutionForwardAlgorithm times fastest, then
//                                 cudnnAddTensor for the bias; FP32 FMA math only, or, with
//                                 allow_tensor_cores, cuDNN's default math (TF32 tensor cores on
//                                 Ampere and later);
//   cublas_im2col_conv2d_forward: the textbook lowering: an im2col kernel writes the column
//                                 matrices cols (B, I k k, Ho Wo), one strided-batched SGEMM
//                                 y[b] (O x Ho Wo) = w (O x I k k) * cols[b], a kernel adds bias.
// Shapes: x (B, I, H, W), w (O, I, k, k), bias (O) or nullptr, y (B, O, Ho, Wo), as conv2d.cuh.
#include <cublas_v2.h>
#include <cudnn.h>

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>

#include "engine/core/error.hpp"
#include "kernels/common.cuh"
#include "kernels/conv2d.cuh"
#include "kernels/device_buffer.hpp"

#define PS_CUDNN_CHECK(call)                                                    \
  do {                                                                          \
    const cudnnStatus_t ps_cudnn_status_ = (call);                              \
    if (ps_cudnn_status_ != CUDNN_STATUS_SUCCESS) {                             \
      PS_FAIL("cuDNN call `{}` failed at {}:{}: {}", #call, __FILE__, __LINE__, \
              cudnnGetErrorString(ps_cudnn_status_));                           \
    }                                                                           \
  } while (0)

#define PS_CUBLAS_CHECK(call)                                                                    \
  do {                                                                                           \
    const cublasStatus_t ps_cublas_status_ = (call);                                             \
    if (ps_cublas_status_ != CUBLAS_STATUS_SUCCESS) {                                            \
      PS_FAIL("cuBLAS call `{}` failed at {}:{}: {} ({})", #call, __FILE__, __LINE__,            \
              cublasGetStatusName(ps_cublas_status_), cublasGetStatusString(ps_cublas_status_)); \
    }                                                                                            \
  } while (0)

namespace pillarseg::bench {

namespace {

constexpr int kThreads = 256;

// cols (B, I k k, Ho Wo): cols[b, (i, ky, kx), (oy, ox)] = x[b, i, oy + ky - pad, ox + kx - pad],
// 0 outside the image; one thread per element.
__global__ void __launch_bounds__(kThreads)
    im2col_kernel(const float* __restrict__ x, float* __restrict__ cols, cuda::Conv2dShape s,
                  std::int64_t out_height, std::int64_t out_width) {
  const std::int64_t pixels = out_height * out_width;
  const std::int64_t taps = s.kernel * s.kernel;
  const std::int64_t total = s.batch * s.in_channels * taps * pixels;
  for (std::int64_t e = std::int64_t{blockIdx.x} * kThreads + threadIdx.x; e < total;
       e += std::int64_t{gridDim.x} * kThreads) {
    const std::int64_t p = e % pixels;
    const std::int64_t r = e / pixels % (s.in_channels * taps);
    const std::int64_t b = e / pixels / (s.in_channels * taps);
    const std::int64_t i = r / taps;
    const std::int64_t ky = r % taps / s.kernel;
    const std::int64_t kx = r % s.kernel;
    const std::int64_t iy = p / out_width + ky - s.pad;
    const std::int64_t ix = p % out_width + kx - s.pad;
    cols[e] = iy >= 0 && iy < s.height && ix >= 0 && ix < s.width
                  ? x[((b * s.in_channels + i) * s.height + iy) * s.width + ix]
                  : 0.0f;
  }
}

// y (B, O, pixels) += bias[o].
__global__ void __launch_bounds__(kThreads)
    add_bias_kernel(float* __restrict__ y, const float* __restrict__ bias, std::int64_t channels,
                    std::int64_t pixels, std::int64_t total) {
  for (std::int64_t e = std::int64_t{blockIdx.x} * kThreads + threadIdx.x; e < total;
       e += std::int64_t{gridDim.x} * kThreads) {
    y[e] += bias[e / pixels % channels];
  }
}

dim3 grid_for(std::int64_t total) {
  return dim3(
      static_cast<unsigned>(std::min<std::int64_t>(cuda::ceil_div(total, kThreads), 65536)));
}

class CudnnConvolution {
 public:
  CudnnConvolution(const cuda::Conv2dShape& s, bool allow_tensor_cores) {
    PS_CUDNN_CHECK(cudnnCreate(&handle_));
    PS_CUDNN_CHECK(cudnnCreateTensorDescriptor(&x_desc_));
    PS_CUDNN_CHECK(cudnnCreateTensorDescriptor(&y_desc_));
    PS_CUDNN_CHECK(cudnnCreateTensorDescriptor(&bias_desc_));
    PS_CUDNN_CHECK(cudnnCreateFilterDescriptor(&w_desc_));
    PS_CUDNN_CHECK(cudnnCreateConvolutionDescriptor(&conv_desc_));
    const auto i32 = [](std::int64_t v) { return static_cast<int>(v); };
    PS_CUDNN_CHECK(cudnnSetTensor4dDescriptor(x_desc_, CUDNN_TENSOR_NCHW, CUDNN_DATA_FLOAT,
                                              i32(s.batch), i32(s.in_channels), i32(s.height),
                                              i32(s.width)));
    PS_CUDNN_CHECK(cudnnSetTensor4dDescriptor(y_desc_, CUDNN_TENSOR_NCHW, CUDNN_DATA_FLOAT,
                                              i32(s.batch), i32(s.out_channels),
                                              i32(s.out_height()), i32(s.out_width())));
    PS_CUDNN_CHECK(cudnnSetTensor4dDescriptor(bias_desc_, CUDNN_TENSOR_NCHW, CUDNN_DATA_FLOAT, 1,
                                              i32(s.out_channels), 1, 1));
    PS_CUDNN_CHECK(cudnnSetFilter4dDescriptor(w_desc_, CUDNN_DATA_FLOAT, CUDNN_TENSOR_NCHW,
                                              i32(s.out_channels), i32(s.in_channels),
                                              i32(s.kernel), i32(s.kernel)));
    PS_CUDNN_CHECK(cudnnSetConvolution2dDescriptor(conv_desc_, i32(s.pad), i32(s.pad), 1, 1, 1, 1,
                                                   CUDNN_CROSS_CORRELATION, CUDNN_DATA_FLOAT));
    PS_CUDNN_CHECK(cudnnSetConvolutionMathType(
        conv_desc_, allow_tensor_cores ? CUDNN_DEFAULT_MATH : CUDNN_FMA_MATH));

    cudnnConvolutionFwdAlgoPerf_t results[CUDNN_CONVOLUTION_FWD_ALGO_COUNT];
    int returned = 0;
    PS_CUDNN_CHECK(cudnnFindConvolutionForwardAlgorithm(handle_, x_desc_, w_desc_, conv_desc_,
                                                        y_desc_, CUDNN_CONVOLUTION_FWD_ALGO_COUNT,
                                                        &returned, results));
    bool found = false;
    for (int r = 0; r < returned && !found; ++r) {  // sorted fastest first
      const bool allowed = allow_tensor_cores || results[r].mathType == CUDNN_FMA_MATH;
      if (results[r].status == CUDNN_STATUS_SUCCESS && allowed) {
        algorithm_ = results[r].algo;
        found = true;
      }
    }
    PS_CHECK(found, "cuDNN offers no forward algorithm for this convolution ({} tried)", returned);
    PS_CUDNN_CHECK(cudnnGetConvolutionForwardWorkspaceSize(handle_, x_desc_, w_desc_, conv_desc_,
                                                           y_desc_, algorithm_, &workspace_bytes_));
    workspace_ = cuda::DeviceBuffer<float>(cuda::ceil_div(workspace_bytes_, sizeof(float)));
  }
  ~CudnnConvolution() {
    static_cast<void>(cudnnDestroyConvolutionDescriptor(conv_desc_));
    static_cast<void>(cudnnDestroyFilterDescriptor(w_desc_));
    static_cast<void>(cudnnDestroyTensorDescriptor(bias_desc_));
    static_cast<void>(cudnnDestroyTensorDescriptor(y_desc_));
    static_cast<void>(cudnnDestroyTensorDescriptor(x_desc_));
    static_cast<void>(cudnnDestroy(handle_));
  }
  CudnnConvolution(const CudnnConvolution&) = delete;
  CudnnConvolution& operator=(const CudnnConvolution&) = delete;

  void forward(const float* x, const float* w, const float* bias, float* y, cudaStream_t stream) {
    const float one = 1.0f;
    const float zero = 0.0f;
    PS_CUDNN_CHECK(cudnnSetStream(handle_, stream));
    PS_CUDNN_CHECK(cudnnConvolutionForward(handle_, &one, x_desc_, x, w_desc_, w, conv_desc_,
                                           algorithm_, workspace_.data(), workspace_bytes_, &zero,
                                           y_desc_, y));
    if (bias != nullptr) {
      PS_CUDNN_CHECK(cudnnAddTensor(handle_, &one, bias_desc_, bias, &one, y_desc_, y));
    }
  }

 private:
  cudnnHandle_t handle_ = nullptr;
  cudnnTensorDescriptor_t x_desc_ = nullptr;
  cudnnTensorDescriptor_t y_desc_ = nullptr;
  cudnnTensorDescriptor_t bias_desc_ = nullptr;
  cudnnFilterDescriptor_t w_desc_ = nullptr;
  cudnnConvolutionDescriptor_t conv_desc_ = nullptr;
  cudnnConvolutionFwdAlgo_t algorithm_ = CUDNN_CONVOLUTION_FWD_ALGO_IMPLICIT_GEMM;
  std::size_t workspace_bytes_ = 0;
  cuda::DeviceBuffer<float> workspace_;
};

class CublasIm2colConvolution {
 public:
  explicit CublasIm2colConvolution(const cuda::Conv2dShape& s)
      : shape_(s),
        cols_(static_cast<std::size_t>(s.batch * s.in_channels * s.kernel * s.kernel *
                                       s.out_height() * s.out_width())) {
    PS_CUBLAS_CHECK(cublasCreate(&handle_));
    PS_CUBLAS_CHECK(cublasSetMathMode(handle_, CUBLAS_DEFAULT_MATH));  // FP32, no TF32
  }
  ~CublasIm2colConvolution() { static_cast<void>(cublasDestroy(handle_)); }
  CublasIm2colConvolution(const CublasIm2colConvolution&) = delete;
  CublasIm2colConvolution& operator=(const CublasIm2colConvolution&) = delete;

  void forward(const float* x, const float* w, const float* bias, float* y, cudaStream_t stream) {
    const cuda::Conv2dShape& s = shape_;
    const std::int64_t pixels = s.out_height() * s.out_width();
    const std::int64_t depth = s.in_channels * s.kernel * s.kernel;
    cuda::launch_kernel(im2col_kernel, grid_for(static_cast<std::int64_t>(cols_.size())),
                        dim3(kThreads), 0, stream, x, cols_.data(), s, s.out_height(),
                        s.out_width());
    // Row-major y[b] (O x P) = w (O x D) * cols[b] (D x P) is column-major
    // y[b]^T (P x O) = cols[b]^T (P x D) * w^T (D x O), with the same memory.
    const float one = 1.0f;
    const float zero = 0.0f;
    PS_CUBLAS_CHECK(cublasSetStream(handle_, stream));
    PS_CUBLAS_CHECK(cublasSgemmStridedBatched(
        handle_, CUBLAS_OP_N, CUBLAS_OP_N, static_cast<int>(pixels),
        static_cast<int>(s.out_channels), static_cast<int>(depth), &one, cols_.data(),
        static_cast<int>(pixels), depth * pixels, w, static_cast<int>(depth), 0, &zero, y,
        static_cast<int>(pixels), s.out_channels * pixels, static_cast<int>(s.batch)));
    if (bias != nullptr) {
      const std::int64_t total = s.batch * s.out_channels * pixels;
      cuda::launch_kernel(add_bias_kernel, grid_for(total), dim3(kThreads), 0, stream, y, bias,
                          s.out_channels, pixels, total);
    }
  }

 private:
  cuda::Conv2dShape shape_;
  cuda::DeviceBuffer<float> cols_;
  cublasHandle_t handle_ = nullptr;
};

}  // namespace

std::function<void(cudaStream_t)> cudnn_conv2d_forward(const cuda::Conv2dShape& shape,
                                                       const float* x, const float* w,
                                                       const float* bias, float* y,
                                                       bool allow_tensor_cores) {
  auto convolution = std::make_shared<CudnnConvolution>(shape, allow_tensor_cores);
  return [convolution, x, w, bias, y](cudaStream_t stream) {
    convolution->forward(x, w, bias, y, stream);
  };
}

std::function<void(cudaStream_t)> cublas_im2col_conv2d_forward(const cuda::Conv2dShape& shape,
                                                               const float* x, const float* w,
                                                               const float* bias, float* y) {
  auto convolution = std::make_shared<CublasIm2colConvolution>(shape);
  return [convolution, x, w, bias, y](cudaStream_t stream) {
    convolution->forward(x, w, bias, y, stream);
  };
}

}  // namespace pillarseg::bench
