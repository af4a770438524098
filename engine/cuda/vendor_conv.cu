// The cuDNN and cuBLAS Conv2d engines of vendor_conv.hpp (nvcc only; cuDNN only where CMake
// found it, PILLARSEG_WITH_CUDNN). Shapes as kernels/conv2d.cuh: x (B, I, H, W), w (O, I, k, k),
// bias (O), y (B, O, Ho, Wo); D = I k k taps per output pixel, P = Ho Wo pixels per image.
//
// cuBLAS is column-major and our tensors are row-major: a row-major (r x c) matrix with row
// stride ld is the column-major (c x r) matrix with leading dimension ld, its transpose. Each
// GEMM below is written on those column-major views.
#include <cublas_v2.h>
#if defined(PILLARSEG_WITH_CUDNN)
#include <cudnn.h>
#endif

#include <algorithm>
#include <array>
#include <climits>
#include <cstddef>
#include <cstdint>
#include <map>
#include <memory>
#include <string>

#include "core/error.hpp"
#include "engine/cuda/vendor_conv.hpp"
#include "kernels/common.cuh"
#include "kernels/device_buffer.hpp"

#define PS_CUBLAS_CHECK(call)                                                                    \
  do {                                                                                           \
    const cublasStatus_t ps_cublas_status_ = (call);                                             \
    if (ps_cublas_status_ != CUBLAS_STATUS_SUCCESS) {                                            \
      PS_FAIL("cuBLAS call `{}` failed at {}:{}: {} ({})", #call, __FILE__, __LINE__,            \
              cublasGetStatusName(ps_cublas_status_), cublasGetStatusString(ps_cublas_status_)); \
    }                                                                                            \
  } while (0)

#if defined(PILLARSEG_WITH_CUDNN)
#define PS_CUDNN_CHECK(call)                                                    \
  do {                                                                          \
    const cudnnStatus_t ps_cudnn_status_ = (call);                              \
    if (ps_cudnn_status_ != CUDNN_STATUS_SUCCESS) {                             \
      PS_FAIL("cuDNN call `{}` failed at {}:{}: {}", #call, __FILE__, __LINE__, \
              cudnnGetErrorString(ps_cudnn_status_));                           \
    }                                                                           \
  } while (0)
#endif

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

namespace {

constexpr int kThreads = 256;
// cuBLAS's own workspace, set explicitly so that it never allocates one (inside a graph capture
// in particular): 32 MiB, NVIDIA's recommendation for Hopper (4 MiB before).
constexpr std::size_t kCublasWorkspaceBytes = std::size_t{32} << 20;

dim3 grid_for(std::int64_t total) {
  return dim3(static_cast<unsigned>(
      std::clamp<std::int64_t>(ceil_div(total, std::int64_t{kThreads}), 1, 65536)));
}

// The preconditions both engines share: non-empty, int-sized tensors.
void check_shape(const char* engine, const Conv2dShape& s) {
  PS_CHECK(s.batch > 0 && s.in_channels > 0 && s.out_channels > 0 && s.kernel > 0 && s.pad >= 0 &&
               s.out_height() > 0 && s.out_width() > 0,
           "{} Conv2d: every dimension must be positive, got x ({}, {}, {}, {}), w ({}, {}, {}, "
           "{}), pad {}",
           engine, s.batch, s.in_channels, s.height, s.width, s.out_channels, s.in_channels,
           s.kernel, s.kernel, s.pad);
  const std::int64_t largest = std::max({s.batch * s.in_channels * s.height * s.width,
                                         s.batch * s.out_channels * s.out_height() * s.out_width(),
                                         s.out_channels * s.in_channels * s.kernel * s.kernel});
  PS_CHECK(largest <= INT_MAX, "{} Conv2d: tensors must have fewer than 2^31 elements, got {}",
           engine, largest);
}

// ---- the cuBLAS lowering's kernels, on a band of `rows` output rows from `row0` of image b ----

// Output rows [row0, row0 + rows) of image `image`, Wo = out_width (Conv2dShape's accessors are
// host functions, so the kernels get it here).
struct Band {
  std::int64_t image = 0, row0 = 0, rows = 0, out_width = 0;
};

// cols (D, rows Wo): cols[(i, ky, kx), p] = x[b, i, oy + ky - pad, ox + kx - pad] with
// oy = row0 + p / Wo, ox = p % Wo; 0 outside the image.
__global__ void __launch_bounds__(kThreads)
    im2col_kernel(const float* __restrict__ x, float* __restrict__ cols, Conv2dShape s, Band band) {
  const std::int64_t out_width = band.out_width;
  const std::int64_t pixels = band.rows * out_width;
  const std::int64_t taps = s.kernel * s.kernel;
  const std::int64_t total = s.in_channels * taps * pixels;
  const float* image = x + band.image * s.in_channels * s.height * s.width;
  for (std::int64_t e = std::int64_t{blockIdx.x} * kThreads + threadIdx.x; e < total;
       e += std::int64_t{gridDim.x} * kThreads) {
    const std::int64_t p = e % pixels;
    const std::int64_t r = e / pixels;
    const std::int64_t i = r / taps;
    const std::int64_t ky = r % taps / s.kernel;
    const std::int64_t kx = r % s.kernel;
    const std::int64_t iy = band.row0 + p / out_width + ky - s.pad;
    const std::int64_t ix = p % out_width + kx - s.pad;
    cols[e] = iy >= 0 && iy < s.height && ix >= 0 && ix < s.width
                  ? image[(i * s.height + iy) * s.width + ix]
                  : 0.0f;
  }
}

// dx[b] += col2im(cols): every input pixel the band's taps reach gathers its taps, in (ky, kx)
// order (no atomics: a fixed summation order). The band's output rows [row0, row0 + rows) reach
// the input rows [row0 - pad, row0 + rows - 1 + k - 1 - pad].
__global__ void __launch_bounds__(kThreads)
    col2im_add_kernel(const float* __restrict__ cols, float* __restrict__ dx, Conv2dShape s,
                      Band band) {
  const std::int64_t out_width = band.out_width;
  const std::int64_t pixels = band.rows * out_width;
  const std::int64_t first_reached = band.row0 - s.pad;
  const std::int64_t last_reached = band.row0 + band.rows - 1 + s.kernel - 1 - s.pad;
  const std::int64_t first_row = first_reached > 0 ? first_reached : 0;
  const std::int64_t last_row = last_reached < s.height - 1 ? last_reached : s.height - 1;
  const std::int64_t rows = last_row - first_row + 1;
  const std::int64_t total = s.in_channels * rows * s.width;
  float* image = dx + band.image * s.in_channels * s.height * s.width;
  for (std::int64_t e = std::int64_t{blockIdx.x} * kThreads + threadIdx.x; e < total;
       e += std::int64_t{gridDim.x} * kThreads) {
    const std::int64_t ix = e % s.width;
    const std::int64_t iy = first_row + e / s.width % rows;
    const std::int64_t i = e / s.width / rows;
    float sum = 0.0f;
    for (std::int64_t ky = 0; ky < s.kernel; ++ky) {
      const std::int64_t oy = iy + s.pad - ky;
      if (oy < band.row0 || oy >= band.row0 + band.rows) continue;
      for (std::int64_t kx = 0; kx < s.kernel; ++kx) {
        const std::int64_t ox = ix + s.pad - kx;
        if (ox < 0 || ox >= out_width) continue;
        sum += cols[((i * s.kernel + ky) * s.kernel + kx) * pixels + (oy - band.row0) * out_width +
                    ox];
      }
    }
    image[(i * s.height + iy) * s.width + ix] += sum;
  }
}

// y (B, O, P) += bias[o].
__global__ void __launch_bounds__(kThreads)
    add_bias_kernel(float* __restrict__ y, const float* __restrict__ bias, std::int64_t channels,
                    std::int64_t pixels, std::int64_t total) {
  for (std::int64_t e = std::int64_t{blockIdx.x} * kThreads + threadIdx.x; e < total;
       e += std::int64_t{gridDim.x} * kThreads) {
    y[e] += bias[e / pixels % channels];
  }
}

// db[o] = sum over b and p of dy[b, o, p]: one block per channel, each thread a strided partial
// sum, then a tree in shared memory (a fixed order).
__global__ void __launch_bounds__(kThreads)
    bias_grad_kernel(const float* __restrict__ dy, float* __restrict__ db, std::int64_t batch,
                     std::int64_t channels, std::int64_t pixels) {
  __shared__ float partial[kThreads];
  const std::int64_t o = blockIdx.x;
  float sum = 0.0f;
  for (std::int64_t e = threadIdx.x; e < batch * pixels; e += kThreads) {
    sum += dy[(e / pixels * channels + o) * pixels + e % pixels];
  }
  partial[threadIdx.x] = sum;
  __syncthreads();
  for (int stride = kThreads / 2; stride > 0; stride /= 2) {
    if (static_cast<int>(threadIdx.x) < stride)
      partial[threadIdx.x] += partial[threadIdx.x + stride];
    __syncthreads();
  }
  if (threadIdx.x == 0) db[o] = partial[0];
}

// ---- cuBLAS ----

class CublasConv2d final : public Conv2dEngine {
 public:
  explicit CublasConv2d(const VendorConvOptions& options) {
    PS_CHECK(options.workspace_limit_bytes >= sizeof(float),
             "cuBLAS Conv2d: workspace_limit_bytes (the cols buffer) must hold at least one float, "
             "got {} bytes",
             options.workspace_limit_bytes);
    cols_ = DeviceBuffer<float>(options.workspace_limit_bytes / sizeof(float));
    library_workspace_ = DeviceBuffer<float>(kCublasWorkspaceBytes / sizeof(float));
    PS_CUBLAS_CHECK(cublasCreate(&handle_));
    // CUBLAS_DEFAULT_MATH is FP32 (no TF32 since CUDA 11); TF32 only when asked for.
    const cublasStatus_t math = cublasSetMathMode(
        handle_, options.allow_tensor_cores ? CUBLAS_TF32_TENSOR_OP_MATH : CUBLAS_DEFAULT_MATH);
    if (math != CUBLAS_STATUS_SUCCESS) {
      static_cast<void>(cublasDestroy(handle_));
      PS_CUBLAS_CHECK(math);
    }
  }
  ~CublasConv2d() override { static_cast<void>(cublasDestroy(handle_)); }
  CublasConv2d(const CublasConv2d&) = delete;
  CublasConv2d& operator=(const CublasConv2d&) = delete;

  std::string name() const override { return "cublas"; }

  VendorConvStats stats() const override {
    return {cols_.bytes() + library_workspace_.bytes(), 2, 0};
  }

  void forward(const float* x, const float* w, const float* bias, float* y, const Conv2dShape& s,
               cudaStream_t stream, bool /*capturing: nothing here allocates*/) override {
    check_shape("cuBLAS", s);
    bind(stream);
    const std::int64_t pixels = s.out_height() * s.out_width();
    const int depth = static_cast<int>(s.in_channels * s.kernel * s.kernel);
    const float one = 1.0f, zero = 0.0f;
    for_each_band(s, [&](const Band& band) {
      const int band_pixels = static_cast<int>(band.rows * s.out_width());
      launch_kernel(im2col_kernel, grid_for(depth * std::int64_t{band_pixels}), dim3(kThreads), 0,
                    stream, x, cols_.data(), s, band);
      // y_band (O x Pb, row stride P) = w (O x D) cols (D x Pb), i.e. column-major
      // y_band^T (Pb x O, ld P) = cols^T (Pb x D, ld Pb) w^T (D x O, ld D).
      float* y_band = y + (band.image * s.out_channels * pixels + band.row0 * s.out_width());
      PS_CUBLAS_CHECK(cublasSgemm(handle_, CUBLAS_OP_N, CUBLAS_OP_N, band_pixels,
                                  static_cast<int>(s.out_channels), depth, &one, cols_.data(),
                                  band_pixels, w, depth, &zero, y_band, static_cast<int>(pixels)));
    });
    if (bias != nullptr) {
      const std::int64_t total = s.batch * s.out_channels * pixels;
      launch_kernel(add_bias_kernel, grid_for(total), dim3(kThreads), 0, stream, y, bias,
                    s.out_channels, pixels, total);
    }
  }

  void backward_data(const float* dy, const float* w, float* dx, const Conv2dShape& s,
                     cudaStream_t stream, bool /*capturing*/) override {
    check_shape("cuBLAS", s);
    bind(stream);
    const std::int64_t pixels = s.out_height() * s.out_width();
    const int depth = static_cast<int>(s.in_channels * s.kernel * s.kernel);
    const float one = 1.0f, zero = 0.0f;
    // The bands' col2im add up: each input pixel may be reached from two bands.
    PS_CUDA_CHECK(cudaMemsetAsync(
        dx, 0,
        static_cast<std::size_t>(s.batch * s.in_channels * s.height * s.width) * sizeof(float),
        stream));
    for_each_band(s, [&](const Band& band) {
      const int band_pixels = static_cast<int>(band.rows * s.out_width());
      // cols (D x Pb) = w^T (D x O) dy_band (O x Pb), i.e. column-major
      // cols^T (Pb x D, ld Pb) = dy_band^T (Pb x O, ld P) * op_T(w^T (D x O, ld D)).
      const float* dy_band =
          dy + (band.image * s.out_channels * pixels + band.row0 * s.out_width());
      PS_CUBLAS_CHECK(cublasSgemm(
          handle_, CUBLAS_OP_N, CUBLAS_OP_T, band_pixels, depth, static_cast<int>(s.out_channels),
          &one, dy_band, static_cast<int>(pixels), w, depth, &zero, cols_.data(), band_pixels));
      const std::int64_t reached_rows = std::min(band.rows + s.kernel - 1, s.height);
      launch_kernel(col2im_add_kernel, grid_for(s.in_channels * reached_rows * s.width),
                    dim3(kThreads), 0, stream, cols_.data(), dx, s, band);
    });
  }

  void backward_weights(const float* x, const float* dy, float* dw, float* db, const Conv2dShape& s,
                        cudaStream_t stream, bool /*capturing*/) override {
    check_shape("cuBLAS", s);
    bind(stream);
    const std::int64_t pixels = s.out_height() * s.out_width();
    const int depth = static_cast<int>(s.in_channels * s.kernel * s.kernel);
    const float one = 1.0f, zero = 0.0f;
    bool first = true;
    for_each_band(s, [&](const Band& band) {
      const int band_pixels = static_cast<int>(band.rows * s.out_width());
      launch_kernel(im2col_kernel, grid_for(depth * std::int64_t{band_pixels}), dim3(kThreads), 0,
                    stream, x, cols_.data(), s, band);
      // dw (O x D) += dy_band (O x Pb) cols^T (Pb x D), i.e. column-major
      // dw^T (D x O, ld D) += op_T(cols^T (Pb x D, ld Pb)) dy_band^T (Pb x O, ld P).
      const float* dy_band =
          dy + (band.image * s.out_channels * pixels + band.row0 * s.out_width());
      PS_CUBLAS_CHECK(cublasSgemm(handle_, CUBLAS_OP_T, CUBLAS_OP_N, depth,
                                  static_cast<int>(s.out_channels), band_pixels, &one, cols_.data(),
                                  band_pixels, dy_band, static_cast<int>(pixels),
                                  first ? &zero : &one, dw, depth));
      first = false;
    });
    if (db != nullptr) {
      launch_kernel(bias_grad_kernel, dim3(static_cast<unsigned>(s.out_channels)), dim3(kThreads),
                    0, stream, dy, db, s.batch, s.out_channels, pixels);
    }
  }

 private:
  // cublasSetStream puts cuBLAS back on its default workspace, so ours is set after it.
  void bind(cudaStream_t stream) {
    if (bound_ && stream == stream_) return;
    PS_CUBLAS_CHECK(cublasSetStream(handle_, stream));
    PS_CUBLAS_CHECK(
        cublasSetWorkspace(handle_, library_workspace_.data(), library_workspace_.bytes()));
    stream_ = stream;
    bound_ = true;
  }

  // Image by image, bands of as many output rows as the cols buffer holds, in order.
  template <class Function>
  void for_each_band(const Conv2dShape& s, const Function& function) const {
    const std::int64_t row_floats = s.in_channels * s.kernel * s.kernel * s.out_width();
    const std::int64_t rows_per_band = std::min<std::int64_t>(
        static_cast<std::int64_t>(cols_.size()) / row_floats, s.out_height());
    PS_CHECK(rows_per_band >= 1,
             "cuBLAS Conv2d: one output row of im2col columns needs {} bytes ({} taps x {} "
             "pixels), the cols buffer holds {}; raise workspace_limit_bytes",
             row_floats * static_cast<std::int64_t>(sizeof(float)),
             s.in_channels * s.kernel * s.kernel, s.out_width(), cols_.bytes());
    for (std::int64_t b = 0; b < s.batch; ++b) {
      for (std::int64_t row0 = 0; row0 < s.out_height(); row0 += rows_per_band) {
        function(Band{b, row0, std::min(rows_per_band, s.out_height() - row0), s.out_width()});
      }
    }
  }

  DeviceBuffer<float> cols_;
  DeviceBuffer<float> library_workspace_;
  cublasHandle_t handle_ = nullptr;
  cudaStream_t stream_ = nullptr;
  bool bound_ = false;
};

#if defined(PILLARSEG_WITH_CUDNN)

// ---- cuDNN ----

// The descriptors of one shape (NCHW float), and the algorithm chosen for each pass: one choice
// for ordinary calls and one for calls inside a graph capture (restricted to algorithms without
// workspace).
struct CudnnPlan {
  template <class Algorithm>
  struct Choice {
    bool made = false;
    Algorithm algorithm{};
    std::size_t workspace_bytes = 0;
  };

  CudnnPlan() {
    PS_CUDNN_CHECK(cudnnCreateTensorDescriptor(&x));
    PS_CUDNN_CHECK(cudnnCreateTensorDescriptor(&y));
    PS_CUDNN_CHECK(cudnnCreateTensorDescriptor(&bias));
    PS_CUDNN_CHECK(cudnnCreateFilterDescriptor(&w));
    PS_CUDNN_CHECK(cudnnCreateConvolutionDescriptor(&conv));
  }
  ~CudnnPlan() {
    static_cast<void>(cudnnDestroyConvolutionDescriptor(conv));
    static_cast<void>(cudnnDestroyFilterDescriptor(w));
    static_cast<void>(cudnnDestroyTensorDescriptor(bias));
    static_cast<void>(cudnnDestroyTensorDescriptor(y));
    static_cast<void>(cudnnDestroyTensorDescriptor(x));
  }
  CudnnPlan(const CudnnPlan&) = delete;
  CudnnPlan& operator=(const CudnnPlan&) = delete;

  // The descriptors of shape `s` with tensors of `type` (NCHW), FP32 compute and `math`.
  void describe(const Conv2dShape& s, cudnnDataType_t type, cudnnMathType_t math) {
    const auto i32 = [](std::int64_t v) { return static_cast<int>(v); };
    PS_CUDNN_CHECK(cudnnSetTensor4dDescriptor(x, CUDNN_TENSOR_NCHW, type, i32(s.batch),
                                              i32(s.in_channels), i32(s.height), i32(s.width)));
    PS_CUDNN_CHECK(cudnnSetTensor4dDescriptor(y, CUDNN_TENSOR_NCHW, type, i32(s.batch),
                                              i32(s.out_channels), i32(s.out_height()),
                                              i32(s.out_width())));
    PS_CUDNN_CHECK(
        cudnnSetTensor4dDescriptor(bias, CUDNN_TENSOR_NCHW, type, 1, i32(s.out_channels), 1, 1));
    PS_CUDNN_CHECK(cudnnSetFilter4dDescriptor(w, type, CUDNN_TENSOR_NCHW, i32(s.out_channels),
                                              i32(s.in_channels), i32(s.kernel), i32(s.kernel)));
    // pad on both axes, stride 1, dilation 1; cross-correlation is what conv2d.cuh computes
    // (CUDNN_CONVOLUTION would flip the kernel). The compute type is float.
    PS_CUDNN_CHECK(cudnnSetConvolution2dDescriptor(conv, i32(s.pad), i32(s.pad), 1, 1, 1, 1,
                                                   CUDNN_CROSS_CORRELATION, CUDNN_DATA_FLOAT));
    PS_CUDNN_CHECK(cudnnSetConvolutionMathType(conv, math));
  }

  cudnnTensorDescriptor_t x = nullptr, y = nullptr, bias = nullptr;
  cudnnFilterDescriptor_t w = nullptr;
  cudnnConvolutionDescriptor_t conv = nullptr;
  Choice<cudnnConvolutionFwdAlgo_t> forward[2];  // [capturing]
  Choice<cudnnConvolutionBwdDataAlgo_t> backward_data[2];
  Choice<cudnnConvolutionBwdFilterAlgo_t> backward_filter[2];
};

class CudnnConv2d final : public Conv2dEngine {
 public:
  explicit CudnnConv2d(const VendorConvOptions& options) : options_(options) {
    PS_CUDNN_CHECK(cudnnCreate(&handle_));
  }
  ~CudnnConv2d() override {
    plans_.clear();
    static_cast<void>(cudnnDestroy(handle_));
  }
  CudnnConv2d(const CudnnConv2d&) = delete;
  CudnnConv2d& operator=(const CudnnConv2d&) = delete;

  std::string name() const override { return "cudnn"; }

  VendorConvStats stats() const override {
    return {workspace_.bytes(), allocations_, static_cast<std::int64_t>(plans_.size())};
  }

  void forward(const float* x, const float* w, const float* bias, float* y, const Conv2dShape& s,
               cudaStream_t stream, bool capturing) override {
    CudnnPlan& plan = plan_for(s);
    PS_CUDNN_CHECK(cudnnSetStream(handle_, stream));
    auto& choice = plan.forward[capturing ? 1 : 0];
    if (!choice.made) {
      cudnnConvolutionFwdAlgoPerf_t results[CUDNN_CONVOLUTION_FWD_ALGO_COUNT];
      int returned = 0;
      if (options_.timed_search && !capturing) {
        PS_CUDNN_CHECK(cudnnFindConvolutionForwardAlgorithm(
            handle_, plan.x, plan.w, plan.conv, plan.y, CUDNN_CONVOLUTION_FWD_ALGO_COUNT, &returned,
            results));
      } else {
        PS_CUDNN_CHECK(cudnnGetConvolutionForwardAlgorithm_v7(
            handle_, plan.x, plan.w, plan.conv, plan.y, CUDNN_CONVOLUTION_FWD_ALGO_COUNT, &returned,
            results));
      }
      choose(choice, results, returned, capturing, "forward", s);
    }
    void* workspace = workspace_for(choice.workspace_bytes, stream, capturing);
    const float one = 1.0f, zero = 0.0f;
    PS_CUDNN_CHECK(cudnnConvolutionForward(handle_, &one, plan.x, x, plan.w, w, plan.conv,
                                           choice.algorithm, workspace, choice.workspace_bytes,
                                           &zero, plan.y, y));
    if (bias != nullptr) {
      PS_CUDNN_CHECK(cudnnAddTensor(handle_, &one, plan.bias, bias, &one, plan.y, y));
    }
  }

  void backward_data(const float* dy, const float* w, float* dx, const Conv2dShape& s,
                     cudaStream_t stream, bool capturing) override {
    CudnnPlan& plan = plan_for(s);
    PS_CUDNN_CHECK(cudnnSetStream(handle_, stream));
    auto& choice = plan.backward_data[capturing ? 1 : 0];
    if (!choice.made) {
      cudnnConvolutionBwdDataAlgoPerf_t results[CUDNN_CONVOLUTION_BWD_DATA_ALGO_COUNT];
      int returned = 0;
      if (options_.timed_search && !capturing) {
        PS_CUDNN_CHECK(cudnnFindConvolutionBackwardDataAlgorithm(
            handle_, plan.w, plan.y, plan.conv, plan.x, CUDNN_CONVOLUTION_BWD_DATA_ALGO_COUNT,
            &returned, results));
      } else {
        PS_CUDNN_CHECK(cudnnGetConvolutionBackwardDataAlgorithm_v7(
            handle_, plan.w, plan.y, plan.conv, plan.x, CUDNN_CONVOLUTION_BWD_DATA_ALGO_COUNT,
            &returned, results));
      }
      choose(choice, results, returned, capturing, "backward-data", s);
    }
    void* workspace = workspace_for(choice.workspace_bytes, stream, capturing);
    const float one = 1.0f, zero = 0.0f;
    PS_CUDNN_CHECK(cudnnConvolutionBackwardData(handle_, &one, plan.w, w, plan.y, dy, plan.conv,
                                                choice.algorithm, workspace, choice.workspace_bytes,
                                                &zero, plan.x, dx));
  }

  void backward_weights(const float* x, const float* dy, float* dw, float* db, const Conv2dShape& s,
                        cudaStream_t stream, bool capturing) override {
    CudnnPlan& plan = plan_for(s);
    PS_CUDNN_CHECK(cudnnSetStream(handle_, stream));
    auto& choice = plan.backward_filter[capturing ? 1 : 0];
    if (!choice.made) {
      cudnnConvolutionBwdFilterAlgoPerf_t results[CUDNN_CONVOLUTION_BWD_FILTER_ALGO_COUNT];
      int returned = 0;
      if (options_.timed_search && !capturing) {
        PS_CUDNN_CHECK(cudnnFindConvolutionBackwardFilterAlgorithm(
            handle_, plan.x, plan.y, plan.conv, plan.w, CUDNN_CONVOLUTION_BWD_FILTER_ALGO_COUNT,
            &returned, results));
      } else {
        PS_CUDNN_CHECK(cudnnGetConvolutionBackwardFilterAlgorithm_v7(
            handle_, plan.x, plan.y, plan.conv, plan.w, CUDNN_CONVOLUTION_BWD_FILTER_ALGO_COUNT,
            &returned, results));
      }
      choose(choice, results, returned, capturing, "backward-filter", s);
    }
    void* workspace = workspace_for(choice.workspace_bytes, stream, capturing);
    const float one = 1.0f, zero = 0.0f;
    PS_CUDNN_CHECK(cudnnConvolutionBackwardFilter(handle_, &one, plan.x, x, plan.y, dy, plan.conv,
                                                  choice.algorithm, workspace,
                                                  choice.workspace_bytes, &zero, plan.w, dw));
    if (db != nullptr) {
      PS_CUDNN_CHECK(cudnnConvolutionBackwardBias(handle_, &one, plan.y, dy, &zero, plan.bias, db));
    }
  }

 private:
  using ShapeKey = std::array<std::int64_t, 7>;

  // The descriptors for `s`, set up on its first use.
  CudnnPlan& plan_for(const Conv2dShape& s) {
    check_shape("cuDNN", s);
    const ShapeKey key{s.batch, s.in_channels, s.height, s.width, s.out_channels, s.kernel, s.pad};
    auto found = plans_.find(key);
    if (found != plans_.end()) return *found->second;
    auto plan = std::make_unique<CudnnPlan>();
    plan->describe(s, CUDNN_DATA_FLOAT,
                   options_.allow_tensor_cores ? CUDNN_DEFAULT_MATH : CUDNN_FMA_MATH);
    return *plans_.emplace(key, std::move(plan)).first->second;
  }

  // The first usable result (cuDNN sorts them, fastest or most promising first): it succeeded,
  // is deterministic, does FP32 math unless tensor cores are allowed, and needs no more workspace
  // than the limit (none at all inside a capture).
  template <class Choice, class Perf>
  void choose(Choice& choice, const Perf* results, int returned, bool capturing, const char* pass,
              const Conv2dShape& s) {
    const std::size_t limit = capturing ? 0 : options_.workspace_limit_bytes;
    for (int r = 0; r < returned; ++r) {
      const Perf& perf = results[r];
      const bool tensor_cores = perf.mathType == CUDNN_TENSOR_OP_MATH ||
                                perf.mathType == CUDNN_TENSOR_OP_MATH_ALLOW_CONVERSION;
      if (perf.status != CUDNN_STATUS_SUCCESS || perf.determinism != CUDNN_DETERMINISTIC ||
          (tensor_cores && !options_.allow_tensor_cores) || perf.memory > limit) {
        continue;
      }
      choice.algorithm = perf.algo;
      choice.workspace_bytes = perf.memory;
      choice.made = true;
      return;
    }
    PS_FAIL(
        "cuDNN offers no deterministic {} algorithm{} with at most {} bytes of workspace for x "
        "({}, {}, {}, {}), w ({}, {}, {}, {}), pad {} ({} candidates){}",
        pass, options_.allow_tensor_cores ? "" : " in FP32 math", limit, s.batch, s.in_channels,
        s.height, s.width, s.out_channels, s.in_channels, s.kernel, s.kernel, s.pad, returned,
        capturing ? "; inside a graph capture only algorithms without workspace qualify" : "");
  }

  // The workspace for `bytes`, grown (never inside a capture: choose() asked for none there).
  void* workspace_for(std::size_t bytes, cudaStream_t stream, bool capturing) {
    if (bytes == 0) return nullptr;
    if (bytes > workspace_.bytes()) {
      PS_CHECK(!capturing, "cuDNN Conv2d: a captured call needs {} bytes of workspace", bytes);
      PS_CUDA_CHECK(cudaStreamSynchronize(stream));  // queued work may still use the old one
      workspace_ = DeviceBuffer<float>();            // freed first: its content is scratch
      workspace_ = DeviceBuffer<float>(ceil_div(bytes, sizeof(float)));
      ++allocations_;
    }
    return workspace_.data();
  }

  VendorConvOptions options_;
  cudnnHandle_t handle_ = nullptr;
  std::map<ShapeKey, std::unique_ptr<CudnnPlan>> plans_;
  DeviceBuffer<float> workspace_;
  std::int64_t allocations_ = 0;
};

// ---- 16-bit peers ----

class CudnnHalfConv final : public HalfConvPeer {
 public:
  explicit CudnnHalfConv(bool bf16) : type_(bf16 ? CUDNN_DATA_BFLOAT16 : CUDNN_DATA_HALF) {
    PS_CUDNN_CHECK(cudnnCreate(&handle_));
  }
  ~CudnnHalfConv() override {
    plans_.clear();
    static_cast<void>(cudnnDestroy(handle_));
  }
  CudnnHalfConv(const CudnnHalfConv&) = delete;
  CudnnHalfConv& operator=(const CudnnHalfConv&) = delete;
  std::string name() const override {
    return type_ == CUDNN_DATA_BFLOAT16 ? "cudnn_bf16" : "cudnn_fp16";
  }

  void forward(const std::uint16_t* x, const std::uint16_t* w, std::uint16_t* y,
               const Conv2dShape& s, cudaStream_t stream) override {
    check_shape("cuDNN 16-bit", s);
    auto& slot =
        plans_[{s.batch, s.in_channels, s.height, s.width, s.out_channels, s.kernel, s.pad}];
    PS_CUDNN_CHECK(cudnnSetStream(handle_, stream));
    if (!slot) {
      slot = std::make_unique<Plan>();
      CudnnPlan& d = slot->descriptors;
      d.describe(s, type_, CUDNN_TENSOR_OP_MATH);
      cudnnConvolutionFwdAlgoPerf_t results[CUDNN_CONVOLUTION_FWD_ALGO_COUNT];
      int returned = 0;
      PS_CUDNN_CHECK(cudnnFindConvolutionForwardAlgorithm(
          handle_, d.x, d.w, d.conv, d.y, CUDNN_CONVOLUTION_FWD_ALGO_COUNT, &returned, results));
      PS_CHECK(returned > 0 && results[0].status == CUDNN_STATUS_SUCCESS,
               "cuDNN: no 16-bit forward algorithm for this shape");
      slot->algorithm = results[0].algo;
      slot->workspace = DeviceBuffer<std::uint8_t>(std::max<std::size_t>(results[0].memory, 1));
    }
    const float one = 1.0f, zero = 0.0f;
    const CudnnPlan& d = slot->descriptors;
    PS_CUDNN_CHECK(cudnnConvolutionForward(handle_, &one, d.x, x, d.w, w, d.conv, slot->algorithm,
                                           slot->workspace.data(), slot->workspace.bytes(), &zero,
                                           d.y, y));
  }

 private:
  // The FP32 engine's descriptors (its bias descriptor and algorithm choices unused), in the
  // 16-bit type, with the algorithm cudnnFind* timed fastest and its workspace.
  struct Plan {
    CudnnPlan descriptors;
    cudnnConvolutionFwdAlgo_t algorithm{};
    DeviceBuffer<std::uint8_t> workspace;
  };
  cudnnDataType_t type_;
  cudnnHandle_t handle_ = nullptr;
  std::map<std::array<std::int64_t, 7>, std::unique_ptr<Plan>> plans_;
};

#endif  // PILLARSEG_WITH_CUDNN

class CublasHalfGemm final : public HalfConvPeer {
 public:
  explicit CublasHalfGemm(bool bf16) : type_(bf16 ? CUDA_R_16BF : CUDA_R_16F) {
    PS_CUBLAS_CHECK(cublasCreate(&handle_));
  }
  ~CublasHalfGemm() override { static_cast<void>(cublasDestroy(handle_)); }
  CublasHalfGemm(const CublasHalfGemm&) = delete;
  CublasHalfGemm& operator=(const CublasHalfGemm&) = delete;
  std::string name() const override {
    return type_ == CUDA_R_16BF ? "cublas_gemm_bf16" : "cublas_gemm_fp16";
  }

  // y (O x B P, row-major, as one (O, B P) matrix) = w (O x K) cols (K x B P); cols is zero (the
  // timing does not depend on the values); y's layout is (O, B, P), the batch-major order aside.
  void forward(const std::uint16_t* /*x*/, const std::uint16_t* w, std::uint16_t* y,
               const Conv2dShape& s, cudaStream_t stream) override {
    const std::int64_t k = s.in_channels * s.kernel * s.kernel,
                       n = s.batch * s.out_height() * s.out_width();
    if (cols_.size() < static_cast<std::size_t>(k * n)) {
      cols_ = DeviceBuffer<std::uint16_t>(static_cast<std::size_t>(k * n));
      PS_CUDA_CHECK(cudaMemset(cols_.data(), 0, cols_.bytes()));
    }
    PS_CUBLAS_CHECK(cublasSetStream(handle_, stream));
    const float one = 1.0f, zero = 0.0f;
    // Column-major: y^T (n x O) = cols^T (n x K) w^T (K x O).
    PS_CUBLAS_CHECK(cublasGemmEx(handle_, CUBLAS_OP_N, CUBLAS_OP_N, static_cast<int>(n),
                                 static_cast<int>(s.out_channels), static_cast<int>(k), &one,
                                 cols_.data(), type_, static_cast<int>(n), w, type_,
                                 static_cast<int>(k), &zero, y, type_, static_cast<int>(n),
                                 CUBLAS_COMPUTE_32F, CUBLAS_GEMM_DEFAULT));
  }

 private:
  cudaDataType_t type_;
  cublasHandle_t handle_ = nullptr;
  DeviceBuffer<std::uint16_t> cols_;
};

}  // namespace

std::unique_ptr<HalfConvPeer> make_vendor_half_conv(ConvolutionImpl impl, bool bf16) {
  switch (impl) {
    case ConvolutionImpl::Cudnn:
#if defined(PILLARSEG_WITH_CUDNN)
      return std::make_unique<CudnnHalfConv>(bf16);
#else
      PS_FAIL("cuDNN 16-bit peer: this build has no cuDNN");
#endif
    case ConvolutionImpl::Cublas:
      return std::make_unique<CublasHalfGemm>(bf16);
    case ConvolutionImpl::Own:
      break;
  }
  PS_FAIL("make_vendor_half_conv: ConvolutionImpl::Own is ours (conv2d_mma_forward)");
}

std::unique_ptr<Conv2dEngine> make_vendor_conv2d(ConvolutionImpl impl,
                                                 const VendorConvOptions& options) {
  switch (impl) {
    case ConvolutionImpl::Cudnn:
#if defined(PILLARSEG_WITH_CUDNN)
      return std::make_unique<CudnnConv2d>(options);
#else
      PS_FAIL(
          "--conv cudnn: this build has no cuDNN (CMake did not find cudnn.h and libcudnn next "
          "to the CUDA toolkit); use --conv own or cublas");
#endif
    case ConvolutionImpl::Cublas:
      return std::make_unique<CublasConv2d>(options);
    case ConvolutionImpl::Own:
      break;
  }
  PS_FAIL(
      "make_vendor_conv2d: ConvolutionImpl::Own is not a vendor library (CudaBackend runs our "
      "kernels for it)");
}

}  // namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE
