// MaxPool2d 2x2 stride 2 (see maxpool2d.cuh). Blocks of 32 x 8 threads cover 32 x 8 outputs
// (forward) or inputs (backward) of one plane, so a warp reads and writes along a row; the grid's
// z axis walks the planes (grid-stride beyond 65535). The forward reads each window row as one
// float2 when every row starts 8-byte aligned (W even, x aligned).
#include "kernels/maxpool2d.cuh"

#include <algorithm>
#include <cstdint>
#include <limits>

#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kTileX = 32;
constexpr int kTileY = 8;
constexpr int kBlockSize = kTileX * kTileY;
constexpr std::int64_t kMaxGridZ = 65535;

dim3 tile_grid(std::int64_t planes, std::int64_t rows, std::int64_t columns) {
  return dim3(static_cast<unsigned>(ceil_div(columns, kTileX)),
              static_cast<unsigned>(ceil_div(rows, kTileY)),
              static_cast<unsigned>(std::min(planes, kMaxGridZ)));
}

void check_sizes(const char* op, std::int64_t planes, std::int64_t height, std::int64_t width) {
  PS_CHECK(planes >= 0 && height >= 0 && width >= 0,
           "{}: expected x (B * C, H, W) with sizes >= 0, given ({}, {}, {})", op, planes, height,
           width);
  PS_CHECK(height * width <= std::numeric_limits<std::int32_t>::max() &&
               ceil_div(width, kTileX) <= std::numeric_limits<int>::max() &&
               ceil_div(height, kTileY) <= 65535,
           "{}: a plane of {} x {} is more than an int32 argmax and the grid address", op, height,
           width);
}

}  // namespace

// Takes `value` (at plane index `index`) over the current best when greater, or when NaN.
static __device__ __forceinline__ void take_max(float value, std::int32_t index, float& best,
                                                std::int32_t& best_index) {
  if (value > best || value != value) {
    best = value;
    best_index = index;
  }
}

static __global__ void __launch_bounds__(kBlockSize)
    maxpool_forward_kernel(const float* x, std::int64_t planes, std::int64_t height,
                           std::int64_t width, bool float2_rows, float* y, std::int32_t* argmax) {
  const std::int64_t out_h = height / 2;
  const std::int64_t out_w = width / 2;
  const std::int64_t ox = std::int64_t{blockIdx.x} * kTileX + threadIdx.x;
  const std::int64_t oy = std::int64_t{blockIdx.y} * kTileY + threadIdx.y;
  if (ox >= out_w || oy >= out_h) return;
  for (std::int64_t plane = blockIdx.z; plane < planes; plane += gridDim.z) {
    const float* in = x + plane * height * width;
    const auto top_index = static_cast<std::int32_t>(2 * oy * width + 2 * ox);
    const auto bottom_index = static_cast<std::int32_t>(top_index + width);
    float2 top;
    float2 bottom;
    if (float2_rows) {
      top = *reinterpret_cast<const float2*>(in + top_index);
      bottom = *reinterpret_cast<const float2*>(in + bottom_index);
    } else {
      top = make_float2(in[top_index], in[top_index + 1]);
      bottom = make_float2(in[bottom_index], in[bottom_index + 1]);
    }
    float best = __uint_as_float(0xff800000u);  // -Inf: PyTorch's start
    std::int32_t best_index = top_index;
    take_max(top.x, top_index, best, best_index);
    take_max(top.y, top_index + 1, best, best_index);
    take_max(bottom.x, bottom_index, best, best_index);
    take_max(bottom.y, bottom_index + 1, best, best_index);
    const std::int64_t o = plane * out_h * out_w + oy * out_w + ox;
    y[o] = best;
    if (argmax != nullptr) argmax[o] = best_index;
  }
}

static __global__ void __launch_bounds__(kBlockSize)
    maxpool_backward_kernel(const float* dy, const std::int32_t* argmax, std::int64_t planes,
                            std::int64_t height, std::int64_t width, float* dx) {
  const std::int64_t out_h = height / 2;
  const std::int64_t out_w = width / 2;
  const std::int64_t ix = std::int64_t{blockIdx.x} * kTileX + threadIdx.x;
  const std::int64_t iy = std::int64_t{blockIdx.y} * kTileY + threadIdx.y;
  if (ix >= width || iy >= height) return;
  const std::int64_t oy = iy / 2;
  const std::int64_t ox = ix / 2;
  const bool in_window = oy < out_h && ox < out_w;
  for (std::int64_t plane = blockIdx.z; plane < planes; plane += gridDim.z) {
    float gradient = 0.0f;
    if (in_window) {
      const std::int64_t o = plane * out_h * out_w + oy * out_w + ox;
      if (argmax[o] == iy * width + ix) gradient = dy[o];
    }
    dx[plane * height * width + iy * width + ix] = gradient;
  }
}

void maxpool2d_forward(const float* x, std::int64_t planes, std::int64_t height, std::int64_t width,
                       float* y, std::int32_t* argmax, cudaStream_t stream) {
  const char* op = "maxpool2d_forward";
  check_sizes(op, planes, height, width);
  const std::int64_t outputs = planes * (height / 2) * (width / 2);
  if (outputs == 0) return;
  PS_CHECK(x != nullptr && y != nullptr,
           "{}: x ({} floats) and y ({} floats) must be device memory", op, planes * height * width,
           outputs);
  const bool float2_rows = width % 2 == 0 && reinterpret_cast<std::uintptr_t>(x) % 8 == 0;
  launch_kernel(maxpool_forward_kernel, tile_grid(planes, height / 2, width / 2),
                dim3(kTileX, kTileY), 0, stream, x, planes, height, width, float2_rows, y, argmax);
}

void maxpool2d_backward(const float* dy, const std::int32_t* argmax, std::int64_t planes,
                        std::int64_t height, std::int64_t width, float* dx, cudaStream_t stream) {
  const char* op = "maxpool2d_backward";
  check_sizes(op, planes, height, width);
  if (planes * height * width == 0) return;
  const std::int64_t outputs = planes * (height / 2) * (width / 2);
  PS_CHECK(dx != nullptr && (outputs == 0 || (dy != nullptr && argmax != nullptr)),
           "{}: dy and argmax ({} values each) and dx ({} floats) must be device memory", op,
           outputs, planes * height * width);
  launch_kernel(maxpool_backward_kernel, tile_grid(planes, height, width), dim3(kTileX, kTileY), 0,
                stream, dy, argmax, planes, height, width, dx);
}

}  // namespace pillarseg::cuda
